"""Field registration: ``forestreg plot --watch`` takes each scan in as a folder fills, waits for
files still being written, ignores what is no scan, registers a copied scan once, refuses a scan of
another plot with the reason, goes on after a kill, and ends with the poses ``forestreg plot``
gives for the same scans."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from forestreg.cli import main
from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.io import write_scan

ROOT = Path(__file__).resolve().parents[1]
FOUR = ((0.0, 0.0), (8.0, 2.0), (-7.0, 5.0), (2.0, -9.0))
NAMES = tuple(f"scan_{k:02d}.laz" for k in range(1, 5))
#: Seconds a test waits for the watcher at most before it fails (never slept through)
PATIENCE_S = 120.0


@pytest.fixture(scope="module")
def scans(tmp_path_factory, sim_plot):
    """The four scans of a small simulated plot (about 140 000 points each) as LAZ files."""
    plot = sim_plot("mixed_temperate", FOUR, seed=31, step=0.4, size=30.0)
    folder = tmp_path_factory.mktemp("scans")
    for s in plot.scans:
        write_scan(s.scan, folder / f"{s.scan.name}.laz")
    return plot, [folder / name for name in NAMES]


@pytest.fixture(scope="module")
def plot_poses(scans, tmp_path_factory):
    """poses.json of ``forestreg plot`` on the four scans, in their order."""
    _, paths = scans
    out = tmp_path_factory.mktemp("plot") / "out"
    assert main(["plot", *map(str, paths), "--out", str(out), "--progress", "none"]) == 0
    return json.loads((out / "poses.json").read_text())["scans"]


def _env() -> dict:
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT.parent), os.environ.get("PYTHONPATH", "")) if p),
    }


def _same_poses(poses: dict, expected: dict) -> None:
    assert set(poses) == set(expected)
    for name, entry in expected.items():
        a, b = np.array(poses[name]["matrix"]), np.array(entry["matrix"])
        if not np.array_equal(a, b):
            rot, trans = rigid_errors(a, b)
            assert rot < 0.001 and trans < 1e-4, f"{name}: {rot} deg, {trans} m from the plot's pose"


def _copier(pairs, *, gap_s: float = 0.0):
    """A thread copying ``(source, target)`` pairs one after the other."""

    def run():
        for source, target in pairs:
            shutil.copyfile(source, target)
            time.sleep(gap_s)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def test_watch_registers_each_scan_as_it_arrives_and_ends_as_plot(scans, plot_poses, tmp_path, capsys):
    plot, paths = scans
    folder, out = tmp_path / "export", tmp_path / "field"
    folder.mkdir()
    copier = _copier([(p, folder / p.name) for p in paths], gap_s=0.3)
    code = main(
        [
            "plot",
            "--watch",
            str(folder),
            "--out",
            str(out),
            "--until-scans",
            "4",
            "--poll",
            "0.1",
            "--progress",
            "jsonl",
        ]
    )
    copier.join()
    captured = capsys.readouterr()
    assert code == 0, captured.err[-2000:]
    lines = [line for line in captured.out.splitlines() if line.startswith("scan_")]
    assert lines[0] == "scan_01.laz: centre (the plot's frame) - 1 of 1 placed"
    for k, line in enumerate(lines[1:], 2):
        assert line.startswith(f"scan_{k:02d}.laz: linked to scan_01.laz (ok, ") and line.endswith(
            f" deg) - {k} of {k} placed"
        ), line
    events = [json.loads(x) for x in captured.err.splitlines() if x.startswith('{"event": "scan"')]
    assert [(e["name"], e["status"], e["placed"]) for e in events] == [
        (n, "centre" if k == 1 else "linked", k) for k, n in enumerate(NAMES, 1)
    ]
    assert all(e["seconds"] is not None for e in events)
    # the folder is a whole plot folder, and its poses are those of ``forestreg plot``
    poses = json.loads((out / "poses.json").read_text())["scans"]
    _same_poses(poses, plot_poses)
    state = json.loads((out / "watch.json").read_text())
    assert {n: f["status"] for n, f in state["files"].items()} == {
        n: "centre" if n == NAMES[0] else "linked" for n in NAMES
    }
    assert all((out / f"{n}.transform.txt").is_file() for n in NAMES) and (out / "report.html").is_file()
    assert not [p for p in out.iterdir() if p.name.startswith(".forestreg-tmp-")]
    for k, name in enumerate(NAMES):  # and near the truth
        rot, trans = rigid_errors(np.array(poses[name]["matrix"]), plot.relative_pose(0, k))
        assert rot < 0.05 and trans < 0.02


def test_partial_file_waits_a_copy_is_registered_once_and_other_files_are_ignored(scans, tmp_path):
    from forestreg.app.watch import watch_plot
    from forestreg.engine.tls.params import RegistrationParams

    _, paths = scans
    folder, out = tmp_path / "export", tmp_path / "field"
    folder.mkdir()
    seen: dict[str, list] = {}
    arrived = {key: threading.Event() for key in ("centre", "waiting", "duplicate")}

    def on_event(event):
        seen.setdefault(event.name, []).append(event)
        if event.status in arrived:
            arrived[event.status].set()

    def feed():
        shutil.copyfile(paths[0], folder / NAMES[0])
        assert arrived["centre"].wait(PATIENCE_S)
        (folder / "notes.txt").write_text("plot 7, north corner\nscanned in the morning\n")
        (folder / "photo.jpg").write_bytes(b"\xff\xd8\xff\xe0" + bytes(100))
        data = paths[1].read_bytes()
        with open(folder / NAMES[1], "wb") as f:  # a slow export: the first 60 % ...
            f.write(data[: int(0.6 * len(data))])
            f.flush()
            assert arrived["waiting"].wait(PATIENCE_S)  # ... seen settled, and waited for
            shutil.copyfile(paths[0], folder / "scan_01 copy.laz")
            assert arrived["duplicate"].wait(PATIENCE_S)
            f.write(data[int(0.6 * len(data)) :])

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    run = watch_plot(folder, out, RegistrationParams(), poll_s=0.1, until_scans=2, on_event=on_event)
    feeder.join(5)
    assert run and run.placed == NAMES[:2] and not run.stopped
    assert [e.status for e in seen[NAMES[1]]] == ["waiting", "linked"], (
        "a partial file is named once, then registered when whole"
    )
    assert "chunk table" in seen[NAMES[1]][0].reason
    assert [(e.status, e.same_as) for e in seen["scan_01 copy.laz"]] == [("duplicate", NAMES[0])]
    for other in ("notes.txt", "photo.jpg"):
        assert [e.status for e in seen[other]] == ["ignored"], other
        assert seen[other][0].message.startswith(f"{other}: not a scan - ")
    poses = json.loads((out / "poses.json").read_text())["scans"]
    assert sorted(poses) == list(NAMES[:2])
    state = json.loads((out / "watch.json").read_text())["files"]
    assert state["scan_01 copy.laz"]["status"] == "duplicate" and state["notes.txt"]["status"] == "ignored"


def test_a_scan_of_another_plot_is_refused_with_the_reason(scans, tmp_path, sim_plot):
    from forestreg.app.watch import watch_plot
    from forestreg.engine.tls.params import RegistrationParams

    _, paths = scans
    other = sim_plot("mixed_temperate", ((0.0, 0.0), (5.0, 0.0)), seed=33, step=0.4, size=30.0).scans[1].scan
    folder, out = tmp_path / "export", tmp_path / "field"
    folder.mkdir()
    events = []
    shutil.copyfile(paths[0], folder / NAMES[0])
    write_scan(other, tmp_path / "elsewhere.laz")
    copier = _copier([(tmp_path / "elsewhere.laz", folder / "zz_other_plot.laz")])
    run = watch_plot(folder, out, RegistrationParams(), poll_s=0.1, until_scans=2, on_event=events.append)
    copier.join()
    assert not run and run.placed == (NAMES[0],) and "zz_other_plot.laz" in run.aside
    refused = [e for e in events if e.name == "zz_other_plot.laz"]
    assert [e.status for e in refused] == ["refused"]
    assert "shares no trunk shadows" in refused[0].reason and "beyond a chance match" in refused[0].reason
    assert "another plot" in refused[0].message
    assert sorted(json.loads((out / "poses.json").read_text())["scans"]) == [NAMES[0]]
    assert json.loads((out / "watch.json").read_text())["files"]["zz_other_plot.laz"]["status"] == "refused"


def test_a_scan_that_shares_trunks_but_does_not_link_gets_the_reason_and_where_to_stand(scans, tmp_path):
    """With an ICP fitness no pair reaches, the second scan's trunk shadows match the centre's
    (not another plot) but its link fails: the line says so and names a position that links."""
    from forestreg.app.watch import watch_plot
    from forestreg.engine.tls.params import RegistrationParams

    _, paths = scans
    folder, out = tmp_path / "export", tmp_path / "field"
    folder.mkdir()
    shutil.copyfile(paths[0], folder / NAMES[0])
    shutil.copyfile(paths[1], folder / NAMES[1])
    events = []
    run = watch_plot(
        folder, out, RegistrationParams(icp_min_fitness=0.99), poll_s=0.1, until_scans=2, on_event=events.append
    )
    assert not run and run.placed == (NAMES[0],)
    event = events[-1]
    assert event.name == NAMES[1] and event.status == "not linked" and event.advice is not None
    assert (
        event.message.startswith(f"{NAMES[1]}: not linked - shares ")
        and f"trunk shadows with {NAMES[0]}, but ICP fitness" in event.message
    )
    assert event.message.endswith(f"stand between them, near ({event.advice[0]:.1f}, {event.advice[1]:.1f})")
    assert event.placed == 1 and event.total == 2


def _watcher(folder: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "forestreg.cli",
            "plot",
            "--watch",
            str(folder),
            "--out",
            str(out),
            "--poll",
            "0.1",
            "--progress",
            "none",
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )


def _read_until(proc: subprocess.Popen, prefix: str) -> list[str]:
    """stdout lines of ``proc`` up to the one starting with ``prefix``."""
    lines: list[str] = []
    deadline = time.monotonic() + PATIENCE_S
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line.rstrip("\n"))
        if line.startswith(prefix):
            return lines
    proc.kill()
    raise AssertionError(f"no line starting with {prefix!r}: {lines} {proc.stderr.read()[-2000:]}")


def test_a_killed_watch_goes_on_from_the_scans_placed(scans, plot_poses, tmp_path):
    _, paths = scans
    folder, out = tmp_path / "export", tmp_path / "field"
    folder.mkdir()
    proc = _watcher(folder, out)
    try:
        shutil.copyfile(paths[0], folder / NAMES[0])
        shutil.copyfile(paths[1], folder / NAMES[1])
        _read_until(proc, f"{NAMES[1]}: linked")
        shutil.copyfile(paths[2], folder / NAMES[2])  # arrives, and the watch is killed while it works on it
        time.sleep(0.5)
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    proc.stdout.close()
    proc.stderr.close()
    assert sorted(json.loads((out / "watch.json").read_text())["files"])[:2] == list(NAMES[:2])
    shutil.copyfile(paths[3], folder / NAMES[3])
    again = subprocess.run(
        [
            sys.executable,
            "-m",
            "forestreg.cli",
            "plot",
            "--watch",
            str(folder),
            "--out",
            str(out),
            "--poll",
            "0.1",
            "--progress",
            "none",
            "--until-scans",
            "4",
        ],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=300,
    )
    assert again.returncode == 0, again.stderr[-2000:]
    lines = [line for line in again.stdout.splitlines() if line.startswith("scan_")]
    assert [line.split(":")[0] for line in lines] == list(NAMES[2:]), (
        "the placed scans are kept, the others taken in once"
    )
    assert lines[-1].endswith("4 of 4 placed")
    project = json.loads((out / "project.json").read_text())
    assert [s["name"] for s in project["scans"]] == list(NAMES)
    _same_poses(json.loads((out / "poses.json").read_text())["scans"], plot_poses)


def test_ctrl_c_ends_a_watch_with_its_folder_whole(scans, tmp_path):
    _, paths = scans
    folder, out = tmp_path / "export", tmp_path / "field"
    folder.mkdir()
    shutil.copyfile(paths[0], folder / NAMES[0])
    proc = _watcher(folder, out)
    try:
        _read_until(proc, f"{NAMES[0]}: centre")
        proc.send_signal(signal.SIGINT)
        out_text, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "stopped: 1 of 1 scans placed" in out_text
    assert json.loads((out / "poses.json").read_text())["scans"][NAMES[0]]["status"] == "ok"
    assert not [p for p in out.iterdir() if p.name.startswith(".forestreg-tmp-")]


@pytest.mark.parametrize(
    "args, says",
    [
        (["--watch", "{folder}", "--out", "{out}", "{scan}"], "give no scan files"),
        (["--watch", "{folder}", "--out", "{out}", "--pairs", "all"], "not with --watch"),
        (["--watch", "{folder}/missing", "--out", "{out}"], "no such folder"),
        (["--out", "{out}", "--until-scans", "2", "{scan}", "{scan}"], "--until-scans goes with --watch"),
        (["--out", "{out}"], "plot needs scan files"),
        (["--watch", "{folder}", "--out", "{folder}"], "--out"),
    ],
)
def test_bad_watch_usage_is_one_line_and_exit_2(args, says, tmp_path, capsys):
    folder = tmp_path / "export"
    folder.mkdir()
    values = {"folder": str(folder), "out": str(tmp_path / "field"), "scan": str(tmp_path / "a.laz")}
    code = main(["plot", *[a.format(**values) for a in args], "--progress", "none"])
    err = capsys.readouterr().err
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err


def test_a_watch_job_of_the_service_streams_one_event_per_scan(scans, tmp_path):
    """The job service runs ``plot --watch`` as any job: its scan events reach the job's event
    stream as they are."""
    from forestreg.cli import build_parser
    from forestreg.service.jobs import JobManager, parse_event, use_parser
    from forestreg.service.store import JobStore

    assert parse_event('{"event": "scan", "name": "a.laz", "status": "linked"}')["status"] == "linked"
    _, paths = scans
    folder, out = tmp_path / "export", tmp_path / "field"
    folder.mkdir()
    shutil.copyfile(paths[0], folder / NAMES[0])
    use_parser(build_parser)
    manager = JobManager(JobStore(tmp_path / "state" / "jobs.db"), workers=1)
    manager.start()
    try:
        job = manager.submit(
            ["plot", "--watch", str(folder), "--out", str(out), "--until-scans", "1", "--poll", "0.1"],
            cwd=str(tmp_path),
        )
        deadline = time.monotonic() + PATIENCE_S
        while time.monotonic() < deadline and manager.store.get(job)["status"] not in ("done", "error", "cancelled"):
            time.sleep(0.2)
        assert manager.store.get(job)["status"] == "done", manager.store.get(job)
        scan_events = [e for _, e in manager.store.events(job) if e.get("event") == "scan"]
        assert [(e["name"], e["status"]) for e in scan_events] == [(NAMES[0], "centre")]
    finally:
        manager.shutdown()
