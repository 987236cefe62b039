"""Fault injection: every command against bad input, wrong paths, unwritable or full destinations,
Ctrl-C and SIGKILL mid-run, and two runs into one folder.

Each test asserts what the README's "Reliability" section promises: the exit code (2 bad input, 1
the data do not allow it, 130 interrupted), one line on stderr (never a traceback), inputs
byte-identical, and output folders complete (a previous result or the new one) or absent.

Fast by construction: tiny simulated scans (30 m plot, 0.5 deg steps); where a test is about the
output side only, the registration is replaced by a result computed once.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from forestreg.cli import build_parser, main
from forestreg.engine.core.errors import TransformError
from forestreg.engine.core.transform import check_rigid, read_matrix, rigid_errors
from forestreg.engine.io import read_scan, write_points, write_scan

POSITIONS = ((0.0, 0.0), (6.0, 2.0), (-5.0, 4.0))


# ----------------------------------------------------------------------------- fixtures & helpers


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, sim_plot):
    """Three tiny simulated scans (files), the plot (truth) and a folder of small bad files."""
    plot = sim_plot("planted_conifer", POSITIONS, seed=3, step=0.5, size=30.0)
    folder = tmp_path_factory.mktemp("tiny")
    paths = []
    for s in plot.scans:
        paths.append(folder / f"{s.scan.name}.laz")
        write_scan(s.scan, paths[-1])
    bad = folder / "bad"
    bad.mkdir()
    (bad / "garbage.laz").write_bytes(b"LASF" + b"\x00" * 50)
    (bad / "empty.laz").write_bytes(b"")
    (bad / "text.csv").write_text("not,a\ntable\n")
    m = np.eye(4)
    (bad / "reflect.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n")
    (bad / "scale.txt").write_text("2 0 0 0\n0 2 0 0\n0 0 2 0\n0 0 0 1\n")
    (bad / "nan.txt").write_text("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    (bad / "2x2.txt").write_text("1 0\n0 1\n")
    (bad / "identity.txt").write_text("\n".join(" ".join(str(v) for v in r) for r in m) + "\n")
    (bad / "other.txt").write_text("a user's notes\n")
    _other_program_e57(bad / "scanner.e57")
    _count_lies(paths[0], bad / "count_lies.las")
    write_points(bad / "in_km.laz", read_scan(paths[0]).points / 1000.0)
    return plot, paths, bad


def _count_lies(scan: Path, path: Path) -> None:
    """``scan`` as a LAS file whose header announces 100 points of the many that follow."""
    import struct

    import laspy

    laspy.read(scan).write(path, do_compress=False)
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 107, 100)
    if data[25] >= 4:  # LAS 1.4: the 64-bit count too
        struct.pack_into("<Q", data, 247, 100)
    path.write_bytes(bytes(data))


def _other_program_e57(path: Path) -> None:
    """A small valid E57 file written by another program (no forestreg description)."""
    import pye57

    rng = np.random.default_rng(0)
    e57 = pye57.E57(str(path), mode="w")
    e57.write_scan_raw({k: rng.random(500) for k in ("cartesianX", "cartesianY", "cartesianZ")}, name="station 1")
    e57.close()


@pytest.fixture(scope="module")
def pair_result(tiny):
    """The tiny pair registered once through the engine (scan_01 <- scan_02)."""
    from forestreg.engine.tls.pair import register

    _, paths, _ = tiny
    result = register(read_scan(paths[0]), read_scan(paths[1]))
    assert result.ok, result.reason
    return result


@pytest.fixture
def fast_register(monkeypatch, pair_result):
    """Replace the pair registration by the cached result (tests about the output side only)."""
    import forestreg.engine.tls.pair as pair

    state = {"result": pair_result}

    def fake_register(reference, moving, *args, **kwargs):
        for source in (reference, moving):  # the command hands over readers: read as the engine would
            if callable(source):
                source()
        return state["result"]

    monkeypatch.setattr(pair, "register", fake_register)
    return state


def _hash(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _tree(folder: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under ``folder`` (its full state)."""
    return {str(p.relative_to(folder)): _hash(p) for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def _error_lines(err: str) -> list[str]:
    """The lines of stderr that are not JSON progress events or logged warnings."""
    return [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("{") and not ln.startswith("WARNING ")]


def _assert_one_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = _error_lines(err)
    assert len(lines) == 1, f"expected one line, got {lines}"
    return lines[0]


def _leftovers(folder: Path) -> list[str]:
    return [p.name for p in Path(folder).iterdir() if p.name.startswith(".forestreg-tmp")]


def _cli(*args: str, stderr=subprocess.PIPE) -> subprocess.Popen:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([p for p in sys.path if p] + [env.get("PYTHONPATH", "")])
    # Ctrl-C as from a terminal, even when the tests themselves run with SIGINT ignored (nohup, "&")
    env["FORESTREG_INTERRUPTIBLE"] = "1"
    return subprocess.Popen(
        [sys.executable, "-m", "forestreg.cli", *args], stdout=subprocess.DEVNULL, stderr=stderr, text=True, env=env
    )


def _wait_for_progress(proc: subprocess.Popen, min_fraction: float, timeout_s: float = 300.0) -> list[dict]:
    """Read JSON progress events from ``proc``'s stderr until one reaches ``min_fraction``."""
    events = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        line = proc.stderr.readline()
        if not line:
            break
        if line.startswith("{"):
            events.append(json.loads(line))
            if events[-1].get("event") == "progress" and events[-1]["fraction"] >= min_fraction:
                return events
    raise AssertionError(f"no progress to {min_fraction} (events: {events[-3:]})")


# ----------------------------------------------------------------------------- bad input: exit 2, one line, nothing written


def _pair_into_out(command: str, *options: str) -> list[str]:
    """``command A B --out O options``: the two tiny scans into a fresh output folder."""
    return [command, "{A}", "{B}", "--out", "{O}", *options]


BAD_INPUT = {
    "zero --up": _pair_into_out("register", "--up=0,0,0"),
    "NaN --up": _pair_into_out("register", "--up=nan,0,1"),
    "negative --dr": _pair_into_out("register", "--dr", "-4"),
    "short --scanner-position": _pair_into_out("register", "--scanner-position", "1,2"),
    "three --up": _pair_into_out("register", "--up=0,0,1", "--up=0,0,1", "--up=0,0,1"),
    "unknown unit": _pair_into_out("register", "--units", "km"),
    "missing scan": ["register", "{A}", "{X}/missing.laz", "--out", "{O}"],
    "garbage scan": ["register", "{A}", "{X}/garbage.laz", "--out", "{O}"],
    "empty scan": ["register", "{A}", "{X}/empty.laz", "--out", "{O}"],
    "--out is an input": ["register", "{A}", "{B}", "--out", "{B}"],
    "--out is a file": ["register", "{A}", "{B}", "--out", "{X}/other.txt"],
    "--out holds other files": ["register", "{A}", "{B}", "--out", "{X}"],
    "--out holds the inputs": ["register", "{A}", "{B}", "--out", "{T}"],
    "plot --merged onto a scan": _pair_into_out("plot", "--merged", "{B}"),
    "plot --merged a folder": _pair_into_out("plot", "--merged", "{X}"),
    "plot unknown --centre": _pair_into_out("plot", "--centre", "nope.laz"),
    "plot unknown --tilted": _pair_into_out("plot", "--tilted", "nope.laz"),
    "plot tilted onto itself": _pair_into_out("plot", "--tilted", "scan_02.laz:scan_02.laz"),
    "plot --loops -3": _pair_into_out("plot", "--loops", "-3"),
    "plot missing scan": ["plot", "{A}", "{X}/missing.laz", "--out", "{O}"],
    "compare unknown --centre": _pair_into_out("compare", "--centre", "nope.laz"),
    "project file forgotten": ["project", "create", "{A}", "{B}"],
    "project unknown --centre": ["project", "create", "{O}.json", "{A}", "{B}", "--centre", "nope.laz"],
    "project missing scan": ["project", "create", "{O}.json", "{A}", "{X}/missing.laz"],
    "project garbage scan": ["project", "create", "{O}.json", "{A}", "{X}/text.csv"],
    "coregister --min-cluster-size 1": _pair_into_out("coregister", "--min-cluster-size", "1"),
    "coregister --out is an input": ["coregister", "{A}", "{B}", "--out", "{A}"],
    "fuse --out is the ground cloud": ["fuse", "{A}", "{B}", "--out", "{A}"],
    "fuse --out not a point file": ["fuse", "{A}", "{B}", "--out", "{O}.json"],
    "fuse --out a user's other scan": ["fuse", "{A}", "{B}", "--out", "{C}"],
    "plot --merged onto a user's other scan": _pair_into_out("plot", "--merged", "{C}"),
    "fuse reflection": ["fuse", "{A}", "{B}", "--transform", "{X}/reflect.txt", "--out", "{O}.laz"],
    "fuse scale 2": ["fuse", "{A}", "{B}", "--transform", "{X}/scale.txt", "--out", "{O}.laz"],
    "fuse NaN matrix": ["fuse", "{A}", "{B}", "--transform", "{X}/nan.txt", "--out", "{O}.laz"],
    "fuse 2x2 matrix": ["fuse", "{A}", "{B}", "--transform", "{X}/2x2.txt", "--out", "{O}.laz"],
    "fuse missing transform": ["fuse", "{A}", "{B}", "--transform", "{X}/none.txt", "--out", "{O}.laz"],
    "trees reflection": ["trees", "{A}", "--out", "{O}", "--transform", "{X}/reflect.txt"],
    "trees missing --field": ["trees", "{A}", "--out", "{O}", "--field", "{X}/missing.csv"],
    "trees garbage --field": ["trees", "{A}", "--out", "{O}", "--field", "{X}/text.csv"],
    "evaluate missing tables": ["evaluate", "{X}/missing.csv", "{X}/missing2.csv", "--out", "{O}"],
    "targets --out is a scan": ["targets", "{A}", "--out", "{A}"],
    "trees a cloud in kilometres": ["trees", "{X}/in_km.laz", "--out", "{O}"],
    "trees a LAS announcing fewer points than it holds": ["trees", "{X}/count_lies.las", "--out", "{O}"],
    "targets --out a user's table": ["targets", "{A}", "--out", "{X}/other.txt"],
    "targets a scan twice": ["targets", "{A}", "{A}", "--out", "{O}.csv"],
    "plot --e57-out onto another program's E57": _pair_into_out("plot", "--e57-out", "{X}/scanner.e57"),
    "simulate --size 0": ["simulate", "planted_conifer", "--out", "{O}", "--size", "0"],
    "simulate --out is a scan": ["simulate", "planted_conifer", "--out", "{A}"],
    "gui --size 0x-5": ["gui", "--size", "0x-5"],
    "register a scan onto itself": ["register", "{A}", "{A}", "--out", "{O}"],
    "coregister a cloud onto itself": ["coregister", "{A}", "{A}", "--out", "{O}"],
    "fuse a cloud with itself": ["fuse", "{A}", "{T}/../{T.name}/{A.name}", "--out", "{O}.laz"],
    "evaluate a table against itself": ["evaluate", "{X}/text.csv", "{X}/text.csv", "--out", "{O}"],
    "--out under a file": _pair_into_out("register")[:-1] + ["{X}/other.txt/sub"],
    "plot of one scan": ["plot", "{A}", "--out", "{O}"],
    "plot with a scan twice": ["plot", "{A}", "{B}", "{A}", "--out", "{O}"],
    "compare without targets": _pair_into_out("compare"),
    "demo --out is a scan": ["demo", "--out", "{A}"],
    "missing --params file": _pair_into_out("register", "--params", "{X}/missing.toml"),
    "infinite --dc": _pair_into_out("register", "--dc", "inf"),
    "unknown command": ["registre", "{A}", "{B}"],
}


@pytest.mark.parametrize("case", sorted(BAD_INPUT))
def test_bad_input_exits_2_with_one_line_before_any_work(case, tiny, tmp_path, capsys):
    _, paths, bad = tiny
    inputs = [*paths, *sorted(bad.iterdir())]
    before = {p: _hash(p) for p in inputs}
    out = tmp_path / "out"
    argv = [a.format(A=paths[0], B=paths[1], C=paths[2], X=bad, O=out, T=paths[0].parent) for a in BAD_INPUT[case]]
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2, (case, captured.err)
    _assert_one_line(captured.err)
    assert {p: _hash(p) for p in inputs} == before, "an input was modified"
    assert not any(tmp_path.iterdir()), f"something was written: {list(tmp_path.iterdir())}"
    assert not _leftovers(paths[0].parent) and not _leftovers(bad)


def test_project_link_and_damaged_project_files_exit_2(tiny, tmp_path, capsys):
    _, paths, _ = tiny
    project = tmp_path / "p.json"
    assert main(["project", "create", str(project), *map(str, paths[:2])]) == 0
    before = _hash(project)
    scans_before = [_hash(p) for p in paths]
    for argv in (
        ["project", "link", str(project), "scan_02.laz", "nope.laz"],
        ["project", "link", str(project), "scan_02.laz", "scan_02.laz"],
        ["project", "link", str(project), "scan_02.laz", "scan_01.laz", "--dr", "-4"],
        ["project", "create", str(project), *map(str, paths[:2])],  # exists already
        ["project", "run", str(project), "--merged", str(paths[1])],  # onto a scan
        ["project", "run", str(project), "--e57-out", str(paths[0])],
    ):
        capsys.readouterr()
        assert main(argv) == 2, argv
        _assert_one_line(capsys.readouterr().err)
        assert _hash(project) == before, f"{argv} changed the project file"
        assert [_hash(p) for p in paths] == scans_before
    # matrices in project files: a 2x2, a scale 2 and a reflection are refused with one line
    data = json.loads(project.read_text())
    for matrix in ([[1, 0], [0, 1]], np.diag([2.0, 2, 2, 1]).tolist(), np.diag([1.0, 1, -1, 1]).tolist()):
        data["links"] = [
            {"moving": "scan_02.laz", "reference": "scan_01.laz", "result": {"status": "ok", "matrix": matrix}}
        ]
        damaged = tmp_path / "damaged.json"
        damaged.write_text(json.dumps(data))
        text = damaged.read_bytes()
        for argv in (["project", "show", str(damaged)], ["project", "run", str(damaged), "-q"]):
            capsys.readouterr()
            assert main(argv) == 2, (matrix, argv)
            line = _assert_one_line(capsys.readouterr().err)
            assert "damaged.json" in line
        assert damaged.read_bytes() == text


def test_georeferenced_scan_without_its_position_and_a_cm_file_are_refused_before_the_work(tiny, tmp_path, capsys):
    """A georeferenced scan without a position has it found from the data; a cloud
    that shows no single scanner (two scans merged) is refused with the hint, like a cm file."""
    from forestreg.engine.core.scan import Scan

    _, paths, _ = tiny
    scan = read_scan(paths[1])
    metres_as_cm = ["--units", "cm"]
    assert main(["register", str(paths[0]), str(paths[1]), "--out", str(tmp_path / "o"), *metres_as_cm]) == 2
    assert "--units" in _assert_one_line(capsys.readouterr().err)
    other = read_scan(paths[2])
    geo, cm = tmp_path / "geo.laz", tmp_path / "cm.laz"
    shift = np.eye(4)
    shift[:3, 3] = [512345.0, 5212345.0, 300.0]
    merged = np.concatenate([scan.points, other.points + [25.0, 0.0, 0.0]]) + shift[:3, 3]
    write_scan(Scan.from_points(merged, name="geo"), geo)
    write_scan(scan, cm, matrix=np.diag([100.0, 100.0, 100.0, 1.0]))
    for moving, hint in ((geo, "--scanner-position"), (cm, "--units")):
        assert main(["register", str(paths[0]), str(moving), "--out", str(tmp_path / "o")]) == 2
        assert hint in _assert_one_line(capsys.readouterr().err)
        assert not (tmp_path / "o").exists()


def test_nan_rows_are_reported(tmp_path, caplog):
    pts = np.random.default_rng(0).uniform(-5, 5, (1000, 3))
    pts[::5] = np.nan
    path = tmp_path / "nan.xyz"
    np.savetxt(path, pts)
    with caplog.at_level("WARNING", logger="forestreg"):
        scan = read_scan(path)
    assert len(scan) == 800
    assert any("200 of 1000 points" in r.getMessage() for r in caplog.records)


# ----------------------------------------------------------------------------- matrices: never an "ok" that is not


@pytest.mark.parametrize(
    "matrix, what",
    [
        (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
        (np.diag([2.0, 2.0, 2.0, 1.0]), "rigid"),
        (np.full((4, 4), np.nan), "NaN"),
        (np.eye(3), "4x4"),
        (np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float), "rigid"),
    ],
)
def test_one_checker_refuses_every_non_rigid_matrix(matrix, what):
    with pytest.raises(TransformError, match=what):
        check_rigid(matrix)


def test_a_nan_result_is_never_ok(fast_register, pair_result, tiny, tmp_path, capsys):
    """Whatever the engine returns, a matrix that is not finite and rigid is withheld as failed."""
    _, paths, _ = tiny
    nan = dataclasses.replace(pair_result, matrix=np.full((4, 4), np.nan))
    fast_register["result"] = nan
    out = tmp_path / "o"
    assert main(["register", str(paths[0]), str(paths[1]), "--out", str(out), "-q"]) == 1
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "failed" and result["matrix"] is None and "NaN" in result["reason"]
    assert not (out / "transform.txt").exists()
    assert "failed" in _assert_one_line(capsys.readouterr().err)


def test_read_matrix_reads_a_failed_result_as_an_error(tmp_path):
    path = tmp_path / "result.json"
    path.write_text(json.dumps({"status": "failed", "matrix": None}))
    with pytest.raises(TransformError, match="no matrix"):
        read_matrix(path)


# ----------------------------------------------------------------------------- units


def test_units_mm_gives_the_matrix_transform_and_vops_in_millimetres(tiny, tmp_path):
    plot, paths, _ = tiny
    mm = []
    for p in paths[:2]:
        mm.append(tmp_path / f"mm_{p.name}")
        write_scan(read_scan(p), mm[-1], matrix=np.diag([1000.0, 1000.0, 1000.0, 1.0]))
    out = tmp_path / "o"
    assert main(["register", str(mm[0]), str(mm[1]), "--out", str(out), "--units", "mm", "-q"]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["unit"] == "mm" and result["unit_scale"] == 0.001
    matrix = np.array(result["matrix"])
    truth = plot.relative_pose(0, 1)
    truth_mm = truth.copy()
    truth_mm[:3, 3] *= 1000.0
    rot, trans = rigid_errors(matrix, truth_mm)
    assert rot < 0.05 and trans < 20.0, f"{rot} deg, {trans} mm"
    assert np.allclose(np.loadtxt(out / "transform.txt"), matrix, atol=1e-6)
    # the matched VOPs of the moving scan land on their reference VOPs in millimetres
    import csv

    ref = {
        int(r["id"]): np.array([float(r["x"]), float(r["y"])])
        for r in csv.DictReader((out / "reference_vops.csv").open())
    }
    rows = [r for r in csv.DictReader((out / "moving_vops.csv").open()) if r["matched_with"]]
    assert len(rows) == result["matched"] >= 4
    for r in rows:
        p = matrix @ np.array([float(r["x"]), float(r["y"]), float(r["z"]), 1.0])
        assert np.linalg.norm(p[:2] - ref[int(r["matched_with"])]) < 250.0  # mm


# ----------------------------------------------------------------------------- output folders are transactions


def test_a_failed_rerun_replaces_the_whole_folder(fast_register, pair_result, tiny, tmp_path, capsys):
    _, paths, _ = tiny
    out = tmp_path / "o"
    assert main(["register", str(paths[0]), str(paths[1]), "--out", str(out), "-q"]) == 0
    assert (out / "transform.txt").exists()
    fast_register["result"] = dataclasses.replace(
        pair_result, status="failed", reason="too few VOPs (test)", matrix=None
    )
    assert main(["register", str(paths[0]), str(paths[1]), "--out", str(out), "-q"]) == 1
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "failed"
    assert not (out / "transform.txt").exists(), "a transform of the earlier run beside a failed result"
    assert not _leftovers(tmp_path)


@pytest.mark.parametrize("fault", ["interrupt", "disk full", "read-only"])
def test_a_run_that_breaks_while_writing_leaves_the_previous_result(
    fault, fast_register, tiny, tmp_path, capsys, monkeypatch
):
    import forestreg.engine.core.atomic as atomic
    import forestreg.engine.io.tables as tables

    _, paths, _ = tiny
    out = tmp_path / "o"
    assert main(["register", str(paths[0]), str(paths[1]), "--out", str(out), "-q"]) == 0
    before = _tree(out)
    calls = {"n": 0}
    real_write = atomic.write_text_atomic

    def breaking_write(path, text):
        calls["n"] += 1
        if calls["n"] == 2:  # after the first CSV
            if fault == "interrupt":
                raise KeyboardInterrupt
            raise OSError(
                errno.ENOSPC if fault == "disk full" else errno.EROFS,
                os.strerror(errno.ENOSPC if fault == "disk full" else errno.EROFS),
            )
        return real_write(path, text)

    monkeypatch.setattr(tables, "write_text_atomic", breaking_write)
    monkeypatch.setattr(atomic, "write_text_atomic", breaking_write)
    capsys.readouterr()
    code = main(["register", str(paths[0]), str(paths[1]), "--out", str(out), "-q"])
    assert code == (130 if fault == "interrupt" else 2)
    _assert_one_line(capsys.readouterr().err)
    assert _tree(out) == before, "the earlier complete result was changed"
    assert not _leftovers(tmp_path)


def test_an_unwritable_destination_is_one_line(fast_register, tiny, tmp_path, capsys, monkeypatch):
    """chmod does not stop root: the refusal of the operating system is simulated."""
    import tempfile

    _, paths, _ = tiny

    def refuse(*a, **k):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    assert main(["register", str(paths[0]), str(paths[1]), "--out", str(tmp_path / "o"), "-q"]) == 2
    assert "Permission denied" in _assert_one_line(capsys.readouterr().err)
    assert not (tmp_path / "o").exists()
    monkeypatch.undo()
    monkeypatch.setattr(os, "access", lambda *a, **k: False)
    assert main(["register", str(paths[0]), str(paths[1]), "--out", str(tmp_path / "o"), "-q"]) == 2
    assert "permission denied" in _assert_one_line(capsys.readouterr().err)


# ----------------------------------------------------------------------------- progress and conventions


def test_jsonl_progress_and_global_flags_after_the_command(fast_register, tiny, tmp_path, capsys):
    _, paths, _ = tiny
    out = tmp_path / "o"
    # the fake registration reports no progress: send one event through the same callback
    import forestreg.engine.tls.pair as pair

    real = pair.register

    def with_progress(*a, progress=None, **k):
        progress(0.5, "matching VOPs (coarse)")
        return real(*a, **k)

    pair.register = with_progress
    try:
        code = main(["register", str(paths[0]), str(paths[1]), "--out", str(out), "-v", "--progress", "jsonl"])
    finally:
        pair.register = real
    assert code == 0
    err = capsys.readouterr().err
    events = [json.loads(ln) for ln in err.splitlines() if ln.startswith("{")]
    assert events[0] == {
        "event": "progress",
        "step": "matching-vops",
        "fraction": 0.5,
        "message": "matching VOPs (coarse)",
    }
    assert events[-1]["event"] == "end" and events[-1]["exit_code"] == 0
    assert events[-1]["result"] == str(out.resolve() / "result.json") and events[-1]["message"].startswith("ok:")
    assert err.splitlines()[-1].startswith("{"), "the end event is the last line"


def test_every_option_has_help_text_and_every_command_takes_quiet():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    commands = dict(sub.choices)
    project = commands.pop("project")
    psub = next(a for a in project._actions if a.__class__.__name__ == "_SubParsersAction")
    commands.update({f"project {k}": v for k, v in psub.choices.items()})
    commands.pop("gui")
    for name, p in commands.items():
        options = {s for a in p._actions for s in a.option_strings}
        assert {"-q", "--quiet", "-v", "--progress"} <= options, name
        for a in p._actions:
            assert a.help, f"{name} {a.option_strings or a.dest} has no help"


# ----------------------------------------------------------------------------- whole runs: plot, evaluate


def test_one_unreadable_scan_does_not_stop_the_plot(tiny, tmp_path, capsys):
    _, paths, bad = tiny
    broken = tmp_path / "broken.laz"
    broken.write_bytes((bad / "garbage.laz").read_bytes())
    out = tmp_path / "plot"
    code = main(["plot", str(paths[0]), str(paths[1]), str(broken), "--out", str(out), "--dr", "10", "-q"])
    assert code == 1
    poses = json.loads((out / "poses.json").read_text())["scans"]
    assert poses["scan_02.laz"]["status"] == "ok" and poses["broken.laz"]["status"] == "failed"
    assert "broken.laz" in poses["broken.laz"]["reason"]
    assert (out / "scan_02.laz.transform.txt").exists() and not (out / "broken.laz.transform.txt").exists()


def _table(path: Path, rows, header=("tree_id", "x", "y", "dbh_m", "height_m")):
    import csv

    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


@pytest.fixture
def tree_tables(tmp_path):
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 40, (30, 2))
    dbh = rng.uniform(0.15, 0.6, 30)
    h = 10 + 40 * dbh + rng.normal(0, 1, 30)
    est = _table(tmp_path / "trees.csv", [(f"E{k}", *xy[k], dbh[k] * 1.02, h[k] * 0.97) for k in range(30)])
    return tmp_path, xy, dbh, h, est


def test_evaluate_with_no_shared_ids_fails_honestly(tree_tables, capsys):
    folder, xy, dbh, h, est = tree_tables
    field = _table(folder / "field.csv", [(f"F{k}", *xy[k], dbh[k], h[k]) for k in range(30)])
    assert main(["evaluate", str(est), str(field), "--by", "id", "--out", str(folder / "e")]) == 1
    err = capsys.readouterr().err
    assert "0 of 30 field trees matched" in err and "no shared tree ids" in err
    assert main(["evaluate", str(est), str(field), "--out", str(folder / "e2")]) == 0


@pytest.mark.parametrize(
    "fault, hint", [("heights in feet", "feet"), ("positions in mm", "millimetres"), ("dbh in mm", "millimetres")]
)
def test_evaluate_refuses_field_values_in_another_unit(fault, hint, tree_tables, capsys):
    folder, xy, dbh, h, est = tree_tables
    rows = [(f"F{k}", *xy[k], dbh[k], h[k]) for k in range(30)]
    if fault == "heights in feet":
        rows = [(i, x, y, d, v / 0.3048) for i, x, y, d, v in rows]
    elif fault == "positions in mm":
        rows = [(i, 1000 * x, 1000 * y, d, v) for i, x, y, d, v in rows]
    else:
        rows = [(i, x, y, 1000 * d, v) for i, x, y, d, v in rows]
    field = _table(folder / "field.csv", rows)
    assert main(["evaluate", str(est), str(field), "--out", str(folder / "e")]) == 2
    assert hint in _assert_one_line(capsys.readouterr().err)
    assert not (folder / "e").exists()


# ----------------------------------------------------------------------------- signals and concurrent runs (subprocesses)


def test_errors_in_a_librarys_del_after_ctrl_c_go_to_the_log_not_stderr(monkeypatch, caplog):
    # CI once saw llvmlite's "Exception ignored in ObjectRef.__del__" traceback under the one line:
    # the interrupt had landed inside its constructor. Other unraisable errors still print.
    from forestreg.cli import _quiet_collateral_after_interrupt
    from forestreg.cli.common import INTERRUPTED

    seen = []
    monkeypatch.setattr(sys, "unraisablehook", seen.append)
    _quiet_collateral_after_interrupt()
    _quiet_collateral_after_interrupt()  # once only: no hook wrapping a hook
    hook = sys.unraisablehook
    assert hook is not seen.append
    unraisable = type("U", (), {"object": "ObjectRef.__del__", "exc_value": AttributeError("_as_parameter_")})()
    try:
        INTERRUPTED.set()
        with caplog.at_level("DEBUG", logger="forestreg"):
            hook(unraisable)
        assert seen == [] and "_as_parameter_" in caplog.text
        INTERRUPTED.clear()
        hook(unraisable)
        assert seen == [unraisable]
    finally:
        INTERRUPTED.clear()


def test_ctrl_c_inside_the_import_machinery_is_delivered_again_not_raised_there(monkeypatch):
    # an exception raised between importlib's lock calls can leave the global import lock held:
    # a thread reading a scan beside the engine's import then waited forever (a run hung on Ctrl-C)
    import forestreg.cli as cli
    from forestreg.cli.common import INTERRUPTED

    kills = []
    monkeypatch.setattr(os, "kill", lambda pid, signum: kills.append((pid, signum)))
    monkeypatch.setattr(cli, "_IMPORT_RETRY_S", 0.0)
    previous = signal.signal(signal.SIGINT, cli._interrupt)
    try:
        in_import = type("F", (), {"f_code": type("C", (), {"co_filename": "<frozen importlib._bootstrap>"})()})()
        cli._interrupt(signal.SIGINT, in_import)  # returns: no KeyboardInterrupt inside importlib
        assert INTERRUPTED.is_set()
        deadline = time.monotonic() + 5
        while not kills and time.monotonic() < deadline:
            time.sleep(0.01)
        assert kills == [(os.getpid(), signal.SIGINT)]
        with pytest.raises(KeyboardInterrupt):  # anywhere else: raised at once
            cli._interrupt(signal.SIGINT, sys._getframe())
    finally:
        signal.signal(signal.SIGINT, previous)
        INTERRUPTED.clear()


def test_malloc_is_tuned_for_a_command_unless_the_user_set_it(monkeypatch):
    import ctypes

    import forestreg.cli as cli

    calls = []

    class Libc:
        def mallopt(self, option, value):
            calls.append((option, value))
            return 1

    monkeypatch.setattr(ctypes, "CDLL", lambda name: Libc())
    monkeypatch.setattr(os, "confstr", lambda name: "glibc 2.36")
    for name in [n for n in os.environ if n.startswith("MALLOC_")] + ["GLIBC_TUNABLES"]:
        monkeypatch.delenv(name, raising=False)
    cli._tune_malloc()
    assert dict(calls) == {
        -3: cli.MALLOC_MMAP_THRESHOLD,
        -1: cli.MALLOC_TRIM_THRESHOLD,
        -2: cli.MALLOC_TOP_PAD,
        -8: cli.MALLOC_ARENA_MAX,
    }
    calls.clear()
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")  # the user's own setting wins: nothing changed
    cli._tune_malloc()
    assert calls == []
    monkeypatch.delenv("MALLOC_ARENA_MAX")
    cli._tune_malloc(cli.MALLOC_LEAN_OPTIONS)  # the trees' tuning: two arenas, nothing else
    assert calls == [(-8, 2)]
    calls.clear()
    monkeypatch.setattr(os, "confstr", lambda name: None)  # not glibc (musl, macOS): nothing asked
    cli._tune_malloc()
    assert calls == []


def test_the_command_starts_one_blas_thread_unless_the_user_asks_for_more():
    # OpenBLAS's own threads only wait busily beside the engine's threads (one per core)
    code = (
        "import sys\n"
        "from forestreg.cli import _one_blas_thread\n"
        "_one_blas_thread()\n"
        "import numpy, scipy.linalg, threadpoolctl\n"
        "print(max(p['num_threads'] for p in threadpoolctl.threadpool_info() if p['user_api'] == 'blas'))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["1"]
    if (os.cpu_count() or 1) > 1:  # the user's own setting wins
        done = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            timeout=120,
            env=dict(env, OPENBLAS_NUM_THREADS="2"),
        )
        assert done.returncode == 0, done.stderr
        assert done.stdout.split() == ["2"]


def test_the_command_reads_las_files_without_the_http_client(tmp_path):
    # the forestreg process marks `requests` absent before laspy is imported (laspy's HTTP reading
    # of COPC files only): laspy still reads and writes local files
    import subprocess

    code = (
        "import sys, numpy as np\n"
        "from forestreg.cli import _without_http_client\n"
        "_without_http_client()\n"
        "import laspy, laspy.copc\n"
        "assert laspy.copc.requests is None and sys.modules['requests'] is None\n"
        "h = laspy.LasHeader(point_format=3, version='1.2'); h.scales = [0.01] * 3\n"
        "las = laspy.LasData(h); las.x, las.y, las.z = np.arange(5.0), np.zeros(5), np.ones(5)\n"
        f"las.write({str(tmp_path / 'a.laz')!r})\n"
        f"assert laspy.read({str(tmp_path / 'a.laz')!r}).header.point_count == 5\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_malloc_is_tuned_only_for_registrations_of_small_las_scans(tiny, tmp_path):
    import argparse
    import struct

    import forestreg.cli as cli
    from forestreg.engine.tls.pair import SEQUENTIAL_PREPARE_POINTS

    assert cli.MALLOC_TUNED_MAX_POINTS == SEQUENTIAL_PREPARE_POINTS
    _, paths, _ = tiny
    las = [str(p) for p in paths if str(p).lower().endswith((".las", ".laz"))]
    assert len(las) >= 2
    assert cli._small_scans(argparse.Namespace(command="register", reference=las[0], moving=las[1]))
    assert cli._small_scans(argparse.Namespace(command="plot", scans=las))
    # a header announcing 30 M points (legacy count and the LAS 1.4 count), a text cloud, no file
    big = tmp_path / "big.las"
    head = bytearray(Path(las[0]).read_bytes()[:375]) if las[0].endswith(".las") else bytearray(b"LASF" + bytes(371))
    head[24:26] = bytes([1, 4])
    struct.pack_into("<I", head, 107, 0)
    struct.pack_into("<Q", head, 247, 30_000_000)
    big.write_bytes(bytes(head))
    text = tmp_path / "cloud.xyz"
    text.write_text("0 0 0\n")
    for scans in ([las[0], str(big)], [las[0], str(text)], [las[0], str(tmp_path / "missing.laz")]):
        assert not cli._small_scans(argparse.Namespace(command="plot", scans=scans))


def _earlier_output(folder: Path, command: str, name: str, text: str) -> dict:
    """``folder`` as ``command`` left it in an earlier run (its marker and a file ``name``
    holding ``text``); returns its :func:`_tree`."""
    folder.mkdir()
    (folder / ".forestreg-output").write_text(f"{command}\n")
    (folder / name).write_text(text)
    return _tree(folder)


def test_ctrl_c_mid_run_exits_130_with_one_line_and_leaves_the_previous_result(tiny, tmp_path):
    _, paths, _ = tiny
    out = tmp_path / "o"
    before = _earlier_output(out, "register", "result.json", '{"status": "ok"}\n')
    proc = _cli("register", str(paths[0]), str(paths[1]), "--out", str(out), "--progress", "jsonl")
    _wait_for_progress(proc, 0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    line = _assert_one_line(err)
    assert "interrupted" in line
    end = json.loads(err.strip().splitlines()[-1])
    assert end["event"] == "end" and end["exit_code"] == 130
    assert _tree(out) == before
    assert not _leftovers(tmp_path)


def test_sigkill_mid_plot_then_resume_keeps_the_finished_links(tiny, tmp_path):
    _, paths, _ = tiny
    out = tmp_path / "plot"
    proc = _cli("plot", *map(str, paths), "--out", str(out), "--dr", "10", "-q", stderr=subprocess.DEVNULL)
    project = out / "project.json"
    end = time.monotonic() + 600
    done = None
    while time.monotonic() < end and proc.poll() is None:
        try:
            data = json.loads(project.read_text())
            done = [link for link in data.get("links", []) if link.get("result")]
        except (OSError, ValueError):
            done = None
        if done:
            break
        time.sleep(0.2)
    assert done, "no link finished"
    proc.kill()
    proc.communicate(timeout=60)
    first = done[0]
    assert first["result"]["status"] == "ok", first["result"].get("reason")
    assert json.loads(project.read_text()), "the project file is whole after SIGKILL"
    resumed = _cli("project", "run", str(project), "-q")
    _, err = resumed.communicate(timeout=600)
    assert resumed.returncode in (0, 1), err
    data = json.loads(project.read_text())
    again = next(link for link in data["links"] if link["moving"] == first["moving"] and not link.get("extra"))
    assert json.dumps(again["result"], sort_keys=True) == json.dumps(first["result"], sort_keys=True), (
        "a finished link was run again"
    )
    assert all(link.get("result") for link in data["links"])
    assert (out / "poses.json").exists()


def test_ctrl_c_mid_plot_says_what_it_kept(tiny, tmp_path):
    """Ctrl-C once a link is saved: exit 130 and one line saying the links are kept for the same
    command to resume (not "left as it was before the run": the folder holds project.json)."""
    _, paths, _ = tiny
    out = tmp_path / "plot"
    proc = _cli("plot", *map(str, paths), "--out", str(out), "--dr", "10", "-q")
    end = time.monotonic() + 600
    while time.monotonic() < end and proc.poll() is None:
        try:
            if any(link.get("result") for link in json.loads((out / "project.json").read_text()).get("links", [])):
                break
        except (OSError, ValueError):
            pass
        time.sleep(0.1)
    assert proc.poll() is None, "the plot ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    line = _assert_one_line(err)
    assert "kept in" in line and "resumes" in line and "left as it was" not in line, line
    assert (out / "project.json").is_file()


def test_two_runs_into_one_folder_leave_one_complete_result(tiny, tmp_path):
    _, paths, _ = tiny
    out = tmp_path / "o"
    procs = [_cli("register", str(paths[0]), str(paths[k]), "--out", str(out), "-q", "--dr", "10") for k in (1, 2)]
    codes = [p.wait(timeout=600) for p in procs]
    errs = []
    for p in procs:
        _, err = p.communicate()
        assert "Traceback" not in err
        errs.append(err)
    # one run writes the folder; the other stops at once naming the run that holds it (or, when
    # the first had finished before the second started, both write in turn)
    assert set(codes) <= {0, 1, 2} and sum(c != 2 for c in codes) >= 1, codes
    for code, err in zip(codes, errs):
        if code == 2:
            assert "is being written by another forestreg run" in err, err
    result = json.loads((out / "result.json").read_text())
    assert result["moving_file"] in {str(paths[1].resolve()), str(paths[2].resolve())}
    if result["status"] == "ok":
        assert np.allclose(np.loadtxt(out / "transform.txt"), result["matrix"], atol=1e-8)
    rows = (out / "moving_vops.csv").read_text().strip().splitlines()
    assert len(rows) == result["moving_vops"] + 1, "the CSV belongs to the other run"
    assert not _leftovers(tmp_path)


def test_the_same_pair_gives_the_same_matrix(tiny, pair_result):
    from forestreg.engine.tls.pair import register

    _, paths, _ = tiny
    again = register(read_scan(paths[0]), read_scan(paths[1]))
    assert again.ok and np.array_equal(again.matrix, pair_result.matrix)


def test_an_output_folder_of_another_command_is_not_replaced(tiny, tmp_path, capsys):
    _, paths, _ = tiny
    plot = tmp_path / "plot"
    before = _earlier_output(plot, "plot", "project.json", "{}\n")
    for argv in (
        ["register", str(paths[0]), str(paths[1]), "--out", str(plot)],
        ["simulate", "planted_conifer", "--out", str(plot)],
    ):
        assert main(argv) == 2, argv
        assert "forestreg plot" in _assert_one_line(capsys.readouterr().err)
        assert _tree(plot) == before


def test_an_unexpected_error_is_one_line_and_writes_nothing(tiny, tmp_path, capsys, monkeypatch):
    import forestreg.engine.tls.pair as pair

    _, paths, _ = tiny

    def broken(*a, **k):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(pair, "register", broken)
    assert main(["register", str(paths[0]), str(paths[1]), "--out", str(tmp_path / "o"), "-q"]) == 1
    assert "SVD did not converge" in _assert_one_line(capsys.readouterr().err)
    assert not (tmp_path / "o").exists() and not _leftovers(tmp_path)


def test_tables_and_matrices_are_written_in_the_files_unit(tmp_path):
    """coregister --units mm and register --units mm share these writers: positions in mm."""
    from types import SimpleNamespace

    from forestreg.engine.core.transform import to_file_units, to_metres
    from forestreg.engine.io.tables import write_keypoints_csv, write_vops_csv

    m = np.eye(4)
    m[:3, 3] = [1.5, -2.0, 0.25]
    assert np.allclose(to_file_units(m, 0.001)[:3, 3], [1500.0, -2000.0, 250.0])
    assert np.allclose(to_metres(to_file_units(m, 0.001), 0.001), m)
    shift = np.eye(4)
    shift[:3, 3] = [100.0, 200.0, 10.0]
    kp = SimpleNamespace(xyz=np.array([[1.0, 2.0, 3.0]]), peak_z=np.array([20.0]), cluster_sizes=np.array([50]))
    write_keypoints_csv(tmp_path / "k.csv", kp, shift, np.array([-1]), unit_scale=0.001)
    row = (tmp_path / "k.csv").read_text().splitlines()[1].split(",")
    assert [float(v) for v in row[1:5]] == [101000.0, 202000.0, 13000.0, 30000.0]
    write_vops_csv(
        tmp_path / "v.csv",
        np.array([[1.0, 2.0]]),
        np.array([3.0]),
        shift,
        np.array([0.2]),
        np.array([9]),
        [-1],
        unit_scale=0.01,
    )
    row = (tmp_path / "v.csv").read_text().splitlines()[1].split(",")
    assert [float(v) for v in row[1:4]] == [10100.0, 20200.0, 1300.0] and row[4] == "0.200"


def test_a_plot_of_cm_files_is_refused_before_the_work(tiny, tmp_path, capsys):
    _, paths, _ = tiny
    cm = []
    for p in paths[:2]:
        cm.append(tmp_path / f"cm_{p.name}")
        write_scan(read_scan(p), cm[-1], matrix=np.diag([100.0, 100.0, 100.0, 1.0]))
    assert main(["plot", *map(str, cm), "--out", str(tmp_path / "plot"), "-q"]) == 2
    assert "--units" in _assert_one_line(capsys.readouterr().err)
    assert not (tmp_path / "plot").exists()
