"""Every shell and Python example of README.md and docs/ runs on generated sample data, so that an
example cannot drift from the code.

One test per fenced block (id ``FILE:LINE``). How a block is classified (run, skip with a reason,
printed output) and what a run must show (exit status, the files it promises) is described in
``tests/docs_blocks.py``. The sample data (a TLS plot of three scans, ground-based and UAV clouds
with field records, a re-survey; under the file names of the examples) are simulated once per
session, in about 10 s.
The examples run with a private home folder (the job service's state lives in it; the compiled
kernels stay in the user's cache). Select them with ``-m docs``, leave them out with ``-m "not docs"``.

The printed lines of ``forestreg demo`` in the docs are compared, in format (numbers left out),
with what the product prints for the demo's own output folder, ``demo_out/`` of the checkout
(``FORESTREG_DEMO_OUT`` to point elsewhere), which CI writes before the tests; without it those
blocks are skipped.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from docs_blocks import (  # tests/ is on the path (pytest's rootdir import mode)
    PYTHON,
    ROOT,
    SHELL,
    Block,
    ClassificationError,
    commands_of,
    decide,
    examples,
    promised_paths,
    shape_key,
    shapes_agree,
    shell_script,
    shell_text,
)

pytestmark = pytest.mark.docs

BLOCKS = examples()

#: Examples that fail today because of a product defect someone is fixing; each stays an
#: expected failure (not strict, so a fix turns it into XPASS, a cue to drop it from here) until
#: the product does what the docs say. Keyed by file and a line of the block.
KNOWN_DEFECTS: dict[tuple[str, str], str] = {}

#: Examples that take about 20 s or more on 2 cores (the sample data's 10 s not counted).
SLOW: set[tuple[str, str]] = {
    ("docs/guide/python-api.md", 'forestreg.load_params("params.toml")'),
    ("docs/guide/system-b.md", "from forestreg.engine.coreg.fusion import fuse_scans, write_fused"),
    ("docs/guide/service.md", 'batch = service.run(["batch"'),
    ("README.md", "forestreg batch plots/ --out batch_out --workers 4"),
    ("docs/guide/cli.md", 'forestreg simulate mixed_temperate --out sim --positions "0,0;12,0"'),
}

#: Programs besides forestreg and Python that examples call; an example needing one that is not
#: installed is skipped, saying so.
TOOLS = ("curl", "jq")


def _marks(block: Block) -> list:
    marks = []
    for (path, line), why in KNOWN_DEFECTS.items():
        if block.path == path and line in block.text:
            marks.append(pytest.mark.xfail(reason=f"known product defect: {why}", strict=False))
    if any(block.path == path and line in block.text for path, line in SLOW):
        marks.append(pytest.mark.slow)
    return marks


def test_every_known_defect_and_slow_entry_names_a_block():
    """The tables above follow the docs: an entry whose block is gone is an error."""
    for path, line in list(KNOWN_DEFECTS) + list(SLOW):
        assert any(b.path == path and line in b.text for b in BLOCKS), f"no example of {path} holds {line!r}"


def test_the_harness_finds_the_examples():
    files = {b.path for b in BLOCKS}
    assert "README.md" in files and "docs/guide/cli.md" in files
    assert len(BLOCKS) >= 30


def _block(text: str, language: str = "bash", marker=None) -> Block:
    return Block("docs/new.md", 3, language, text, marker)


def test_an_example_without_a_decision_fails_naming_what_to_decide():
    for text, language, what in (
        ("pip install forestreg\n", "bash", "installation"),
        ("forestreg gui\n", "bash", "the desktop GUI"),
        ("ok: 3 trees\n", "", "an unlabelled block"),
        ("forestreg plot SCAN [SCAN ...] --out DIR [--centre SCAN]\n", "bash", "a synopsis"),
        ("dask scheduler --port 8786\n", "bash", "a cluster"),
        ("ls -l pair/\n", "bash", "commands other than forestreg (ls)"),
    ):
        with pytest.raises(ClassificationError, match="docs-test: skip REASON") as caught:
            decide(_block(text, language))
        assert what in str(caught.value) and "docs/new.md:3" in str(caught.value)
    with pytest.raises(ClassificationError, match="needs a reason"):
        decide(_block("forestreg gui\n", marker="skip"))
    with pytest.raises(ClassificationError, match="does not know"):
        decide(_block("forestreg register a.laz b.laz --out p\n", marker="run quickly"))


def test_forestreg_commands_and_python_run_by_default_and_comments_decide():
    assert decide(_block("forestreg register scan1.laz scan2.laz --out pair\n")).kind == "run"
    assert decide(_block("import forestreg\n", "python")).kind == "run"
    d = decide(_block("curl -s $URL/v1/health\n", marker="run exit=0,1 creates=pair/result.json service timeout=60"))
    assert (d.kind, d.exit_codes, d.creates, d.service, d.timeout) == ("run", (0, 1), ("pair/result.json",), True, 60.0)
    assert decide(_block("pip install x\n", marker="skip (installation)")).reason == "(installation)"
    assert decide(_block("ok: 1\n", "", marker="output demo")).demo


def test_what_an_example_promises():
    block = _block(
        "forestreg register scan1.laz scan2.laz --out pair\n"
        "# pair/result.json (status), pair/transform.txt, and see docs/guide/cli.md\n"
        "forestreg plot scans/*.laz --out plot --merged=plot/all.copc.laz\n"
        "forestreg params --toml > my.toml   # every parameter\n"
    )
    assert promised_paths(block, decide(block)) == [
        "pair",
        "plot",
        "plot/all.copc.laz",
        "my.toml",
        "pair/result.json",
        "pair/transform.txt",
    ]
    py = _block('job = service.submit(["register", "A.laz", "B.laz", "--out", "pair"])\n', "python")
    assert promised_paths(py, decide(py)) == ["pair"]
    assert commands_of("a \\\n  b\n\n# note\nc  # why\n") == ["a b", "c  # why"]
    console = _block(
        "$ forestreg params --toml > my.toml\nprinted\n$ forestreg register a.laz \\\n    b.laz --out p\nok: 3\n",
        "console",
    )
    assert commands_of(shell_text(console)) == [
        "forestreg params --toml > my.toml",
        "forestreg register a.laz b.laz --out p",
    ]
    assert decide(console).kind == "run" and promised_paths(console, decide(console)) == ["my.toml", "p"]


def test_a_demo_line_in_another_format_is_caught():
    printed = (
        "ok: 5 keypoints matched (45 %), canopy correlation 0.90 (margin 0.50 over the best alternative); "
        "decided by the keypoints, tilt 0.00 deg, standard errors 0.011 deg / 0.2 cm -> demo_out/system_b/coregistration/result.json"
    )
    assert shapes_agree(
        "ok: 6 keypoints matched (50 %), canopy correlation 0.91 (margin 0.4 over the best alternative); ...", printed
    )
    assert not shapes_agree(
        "ok: 5 keypoints matched (45 %), canopy correlation 0.90 (margin 0.47 over the best alternative), "
        "standard errors 0.019 deg / 0.3 cm -> demo_out/system_b/coregistration/result.json",
        printed,
    )
    assert shapes_agree(
        "wrote 1,018,074 points to demo_out/system_b/fused.laz", "wrote 998 points to demo_out/system_b/fused.laz"
    )
    assert shape_key(printed) == "ok: # keypoints"


# ----------------------------------------------------------------------------- the session


@pytest.fixture(scope="session")
def docs_session(tmp_path_factory):
    """The sample data, a private home folder and the environment of every example; afterwards
    the job services an example started in that home are stopped."""
    from docs_blocks import make_sample_data

    base = tmp_path_factory.mktemp("docs_examples")
    data = base / "data"
    t0 = time.monotonic()
    make_sample_data(data)
    home = base / "home"
    home.mkdir()
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    env["HOME"] = str(home)
    # the compiled kernels and matplotlib's font cache stay where they are
    env.setdefault("XDG_CACHE_HOME", str(Path.home() / ".cache"))
    for name in ("FORESTREG_SERVICE_DIR", "XDG_DATA_HOME", "XDG_CONFIG_HOME"):
        env.pop(name, None)
    session = SimpleNamespace(data=data, home=home, env=env, data_seconds=time.monotonic() - t0)
    yield session
    _stop_services(home)


def _stop_services(home: Path) -> None:
    """Stop every job service whose state folder lies in ``home`` (started by an example)."""
    for info in home.rglob("server.json"):
        try:
            pid = int(json.loads(info.read_text())["pid"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
        try:
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            continue
        for _ in range(100):
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def _service_state(home: Path) -> Path:
    return home / ".local" / "share" / "forestreg" / "service"


def _run(cmd: list[str], cwd: Path, env: dict, timeout: float) -> tuple[int, str]:
    """Run ``cmd`` in its own process group; the group is killed at the timeout."""
    proc = subprocess.Popen(
        cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        return -1, _without_progress(out or "") + f"\n[docs-test] timed out after {timeout:.0f} s"
    return proc.returncode, _without_progress(out or "")


def _without_progress(text: str) -> str:
    """The output without progress bar lines (kept short in a failure's message)."""
    return "\n".join(line for line in text.replace("\r", "\n").splitlines() if not re.search(r"\d+%\|.*$", line))


# ----------------------------------------------------------------------------- the test


@pytest.mark.parametrize("block", [pytest.param(b, id=b.id, marks=_marks(b)) for b in BLOCKS])
def test_example(block: Block, request, tmp_path):
    try:
        decision = decide(block)
    except ClassificationError as exc:
        decision, problem = None, str(exc)
    if decision is None:
        pytest.fail(problem, pytrace=False)
    if decision.kind == "skip":
        pytest.skip(f"not run: {decision.reason}")
    if decision.kind == "output":
        if not decision.demo:
            pytest.skip("printed output")
        _check_demo_lines(block, tmp_path)
        return
    missing = [
        tool for tool in TOOLS if re.search(rf"(^|[\s(|]){tool}\s", block.text, re.M) and shutil.which(tool) is None
    ]
    if missing:
        pytest.skip(f"needs {', '.join(missing)}, not installed here")
    session = request.getfixturevalue("docs_session")
    _run_example(block, decision, session, tmp_path)


def _run_example(block: Block, decision, session, tmp_path: Path) -> None:
    work = tmp_path / "work"
    shutil.copytree(session.data, work, ignore=shutil.ignore_patterns("variants"))
    promised = promised_paths(block, decision)
    for rel in promised:  # what the example writes is not there before it runs
        target = work / rel
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()
    if decision.service:
        code, out = _run(
            [sys.executable, "-c", "from forestreg.client import connect; connect()"], work, session.env, 120
        )
        assert code == 0, f"the job service did not start:\n{out[-3000:]}"
    if block.language in PYTHON:
        script = tmp_path / "example.py"
        script.write_text(block.text)
        code, out = _run([sys.executable, str(script)], work, session.env, decision.timeout)
        expected = decision.exit_codes[0]
        assert code == expected, (
            f"{block.id}: the Python example ended with exit status {code}, expected {expected}:\n{out[-4000:]}"
        )
    else:
        assert block.language in SHELL
        rc_file = tmp_path / "exit_codes"
        script = tmp_path / "example.sh"
        script.write_text(shell_script(block, rc_file, session.data))
        code, out = _run(["bash", str(script)], work, session.env, decision.timeout)
        commands = commands_of(shell_text(block))
        codes = [int(x) for x in rc_file.read_text().split()] if rc_file.exists() else []
        expected = (
            list(decision.exit_codes) * len(commands) if len(decision.exit_codes) == 1 else list(decision.exit_codes)
        )
        assert len(expected) == len(commands), f"{block.id}: exit={decision.exit_codes} for {len(commands)} commands"
        assert len(codes) == len(commands), (
            f"{block.id}: only {len(codes)} of {len(commands)} commands ended:\n{out[-4000:]}"
        )
        wrong = [
            f"`{c}` ended with exit status {got}, expected {want}"
            for c, got, want in zip(commands, codes, expected)
            if got != want
        ]
        assert not wrong, f"{block.id}: " + "; ".join(wrong) + f"\n{out[-4000:]}"
    missing = [rel for rel in promised if not (work / rel).exists()]
    assert not missing, f"{block.id}: the example promises {missing}, which it did not write:\n{out[-3000:]}"


# ----------------------------------------------------------------------------- the demo's lines


def _demo_out() -> Path:
    return Path(os.environ.get("FORESTREG_DEMO_OUT") or ROOT / "demo_out")


def _demo_lines(demo: Path, tmp_path: Path) -> list[str]:
    """The lines the product prints for the demo's registration, co-registration and evaluation,
    made by its own printing code from the demo's output folder (paths shown as ``demo_out/...``):
    each ``result.json`` stands in for the result object it was written from."""
    from forestreg.app.evaluation import evaluate_tables
    from forestreg.cli.common import Reporter
    from forestreg.cli.coreg import print_coregister
    from forestreg.cli.register import print_register
    from forestreg.engine.coreg.coregister import CoregistrationResult

    shown = Path("demo_out")
    reg = _Record(json.loads((demo / "registration" / "result.json").read_text()))
    co = _Record(json.loads((demo / "system_b" / "coregistration" / "result.json").read_text()))
    buf = io.StringIO()
    problem = None
    try:
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
            print_register(
                _Saved(
                    status=reg["status"],
                    out=shown / "registration",
                    result=reg,
                    figure=demo / "registration" / "registration.png",
                ),
                Reporter("none", "register"),
            )
            line = CoregistrationResult.summary(co)
            print_coregister(
                _Saved(status=co["status"], out=shown / "system_b" / "coregistration", report=None, line=lambda: line),
                Reporter("none", "coregister"),
            )
    except (AttributeError, KeyError, TypeError) as exc:
        problem = (
            f"the printing code reads {str(exc.args[0]) if exc.args else repr(exc)!r}, which the demo's result.json in {demo} does not hold: either that "
            "folder was written by another version (run 'forestreg demo' again) or the code names it otherwise "
            "(teach _Record in tests/test_docs_examples.py the name)"
        )
    if problem:
        pytest.fail(problem, pytrace=False)
    lines = buf.getvalue().splitlines()
    b = demo / "system_b"
    evaluation = evaluate_tables(
        [("ground", b / "trees_ground" / "trees.csv"), ("fused", b / "trees_fused" / "trees.csv")],
        b / "data" / "field.csv",
        tmp_path / "evaluation",
    )
    return lines + list(evaluation.lines)


class _Saved(SimpleNamespace):
    """A stand-in outcome read back from an output folder: true when its status is ok."""

    def __bool__(self) -> bool:
        return self.status == "ok"


class _Record(dict):
    """A saved ``result.json`` read as the result object it was written from: its keys are
    attributes (nested tables too), ``ok`` is its status, and the engine's names that the file
    spells otherwise are mapped."""

    ALIASES = {"n_matched": "matched"}

    def __getattr__(self, name: str):
        if name == "ok":
            return self.get("status") == "ok"
        key = self.ALIASES.get(name, name)
        if key not in self:
            raise AttributeError(name)
        value = self[key]
        return _Record(value) if isinstance(value, dict) else value


def _check_demo_lines(block: Block, tmp_path: Path) -> None:
    demo = _demo_out()
    if not (demo / "registration" / "result.json").is_file() or not (demo / "system_b" / "evaluation").is_dir():
        pytest.skip(f"no demo output in {demo} (CI runs 'forestreg demo --out demo_out' before the tests)")
    printed = _demo_lines(demo, tmp_path)
    by_key = {shape_key(line): line for line in printed}
    compared = 0
    problems = []
    for line in block.text.splitlines():
        if not line.strip() or line.strip() == "...":
            continue
        for word in line.replace(",", " ").split():
            if word.startswith("demo_out/") and not (demo / word[len("demo_out/") :]).exists():
                problems.append(f"{word} (named in {line!r}) is not in the demo's output")
        printed_line = by_key.get(shape_key(line))
        if printed_line is not None:
            compared += 1
            if not shapes_agree(line, printed_line):
                problems.append(f"documented: {line.strip()}\n      printed: {printed_line}")
    assert not problems, f"{block.id}: the demo's lines in the docs differ from what it prints:\n  " + "\n  ".join(
        problems
    )
    assert compared, f"{block.id}: none of the lines is one the test can compare ({sorted(by_key)})"
