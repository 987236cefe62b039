"""The documentation: the site builds strictly, the references generated from the code document
every command, option, parameter and column, the output reference names every key a real
``result.json`` holds, and no user-facing text carries development history."""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _hooks():
    spec = importlib.util.spec_from_file_location("forestreg_docs_hooks", ROOT / "scripts" / "docs_hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _env() -> dict:
    """The environment of a child process that imports this checkout as ``forestreg``."""
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT.parent), os.environ.get("PYTHONPATH", "")) if p),
        "NO_MKDOCS_2_WARNING": "1",
    }


def test_site_builds_strictly(tmp_path):
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install -e '.[docs]')")
    out = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-5000:]
    warnings = [line for line in out.stderr.splitlines() if line.startswith(("WARNING", "ERROR"))]
    assert warnings == []
    site = tmp_path / "site"
    for page in ("reference/cli", "reference/parameters", "reference/columns", "reference/api", "guide/desktop"):
        assert (site / page / "index.html").is_file(), page
    api = (site / "reference" / "api" / "index.html").read_text(encoding="utf-8")
    assert "forestreg.engine.tls.pair.register" in api or 'id="forestreg.engine.tls.pair.register"' in api


def test_references_document_everything():
    assert _hooks().problems() == []


def test_the_command_reference_lists_every_command_and_option():
    from forestreg.cli import build_parser

    hooks = _hooks()
    page = hooks.cli_reference()
    parser = build_parser()
    for name, _, sub in hooks._subcommands(parser):
        assert f"## `forestreg {name}`" in page, name
        if name == "gui":
            continue
        for action in sub._actions:
            for option in action.option_strings:
                if option not in hooks.GLOBAL_FLAGS:
                    assert f"`{option}`" in page, f"{name} {option}"


def test_an_option_without_help_or_a_number_without_unit_is_a_problem(monkeypatch):
    hooks = _hooks()
    parser = argparse.ArgumentParser(prog="forestreg new")
    parser.add_argument("--documented", help="what it does")
    parser.add_argument("--silent")
    issues: list[str] = []
    hooks._command_section("forestreg new", "a new command", parser, issues)
    assert issues == ["'forestreg new': argument --silent has no help text"]

    from forestreg.engine import params as product
    from forestreg.engine.core.params import Params, param_field

    @dataclasses.dataclass(frozen=True)
    class NewParams(Params):
        width_m: float = param_field(1.0, "m", 0.0, None, "a width")
        share: float = param_field(0.5, "", 0.0, 1.0, "a share")
        quiet: float = param_field(0.5, "1", 0.0, 1.0, "")

    @dataclasses.dataclass(frozen=True)
    class Product(Params):
        new: NewParams = NewParams()

    monkeypatch.setattr(product, "ProductParams", Product)
    issues = []
    page = hooks.parameters_reference(issues)
    assert "| `width_m` | 1.0 | m | 0.0 to inf |" in page
    assert issues == ["parameter [new] share (a number) has no unit", "parameter [new] quiet has no help text"]


def test_default_parameter_file_is_current():
    from forestreg.engine.params import params_toml

    shipped = (ROOT / "resources" / "default_params.toml").read_text(encoding="utf-8")
    assert shipped.strip() == params_toml().strip(), (
        "resources/default_params.toml is out of date: run 'forestreg params --toml > resources/default_params.toml'"
    )


def test_the_output_reference_names_every_key_of_a_real_result(tmp_path, sim_plot):
    """A tiny pair registered by the command line: every top-level key of its ``result.json``
    and every file it writes are named in the output reference."""
    from forestreg.engine.io import write_scan

    plot = sim_plot("planted_conifer", ((0.0, 0.0), (7.0, 2.0), (-5.0, 6.0)), seed=3, step=0.5, size=30.0)
    paths = []
    for s in plot.scans[:2]:
        paths.append(tmp_path / f"{s.scan.name}.laz")
        write_scan(s.scan, paths[-1])
    out = tmp_path / "pair"
    run = subprocess.run(
        [sys.executable, "-m", "forestreg.cli", "register", *map(str, paths), "--out", str(out), "-q"],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode in (0, 1), run.stderr
    page = (ROOT / "docs" / "reference" / "outputs.md").read_text(encoding="utf-8")
    result = json.loads((out / "result.json").read_text())
    missing = [k for k in result if f"`{k}`" not in page]
    assert missing == [], f"result.json keys not described in docs/reference/outputs.md: {missing}"
    files = [p.name for p in out.iterdir()]
    assert [f for f in files if f"`{f}`" not in page] == []


def test_the_output_reference_names_every_key_of_a_coregistration_result(tmp_path):
    """A co-registration of two flat clouds (no canopy: it fails at once, its ``result.json``
    holding every key with empty values): every key is named in the output reference."""
    import numpy as np

    from forestreg.engine.core.scan import Scan
    from forestreg.engine.io import write_scan

    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(0, 30, (20000, 2)), rng.normal(0, 0.02, 20000)]
    for name, pts in (("ground", ground), ("uav", ground + [0, 0, 0.1])):
        write_scan(Scan(pts, np.zeros(3), np.zeros(3), name=name), tmp_path / f"{name}.laz")
    out = tmp_path / "coreg"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "forestreg.cli",
            "coregister",
            str(tmp_path / "ground.laz"),
            str(tmp_path / "uav.laz"),
            "--out",
            str(out),
            "-q",
        ],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 1 and "too little canopy" in run.stderr, run.stderr
    page = (ROOT / "docs" / "reference" / "outputs.md").read_text(encoding="utf-8")
    section = page[page.index("### `forestreg coregister`") :]
    result = json.loads((out / "result.json").read_text())
    assert [k for k in result if f"`{k}`" not in section] == []


def test_readme_is_short_and_its_commands_are_the_ci_commands():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 300
    ci = (ROOT / ".ci" / "run").read_text()
    for command in (
        "bash scripts/setup.sh && .venv/bin/forestreg demo --out demo_out",
        "bash scripts/setup.sh && .venv/bin/python -m pytest -q",
    ):
        assert command in readme and command in ci
    for link in re.findall(r"\]\(((?:docs/|CHANGELOG)[^)#]*)", readme):
        assert (ROOT / link).is_file(), link  # a generated page exists only in the built site


HISTORY = re.compile(r"\b(issues? ?#?\d+|sessions? \d+|rounds? \d+ of development)\b", re.I)


def test_no_development_history_in_user_facing_text():
    """Issue numbers and numbered development rounds belong to the git log and CHANGELOG.md, not
    to the README, the docs, or any docstring or comment of the code and tests."""
    files = [ROOT / "README.md", ROOT / "metadata.txt", ROOT / "mkdocs.yml"]
    files += sorted((ROOT / "docs").rglob("*.md"))
    for folder in ("cli", "engine", "plugin", "service", "ui", "tests", "benchmarks", "scripts", "resources"):
        files += sorted((ROOT / folder).rglob("*.py")) + sorted((ROOT / folder).rglob("*.toml"))
    files += [ROOT / "__init__.py", ROOT / "client.py"]
    offenders = []
    for f in files:
        if f.name == "test_docs.py":
            continue
        for n, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1):
            if HISTORY.search(line):
                offenders.append(f"{f.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert offenders == []


def test_a_page_missing_from_the_nav_is_added_to_it(tmp_path):
    hooks = _hooks()
    docs = tmp_path / "docs"
    (docs / "guide").mkdir(parents=True)
    (docs / "index.md").write_text("# Home\n")
    (docs / "notes.md").write_text("Intro\n\n# Design notes\n")
    config = {"nav": [{"Home": "index.md"}], "docs_dir": str(docs)}
    hooks.on_config(config)
    assert config["nav"] == [{"Home": "index.md"}, {"Design notes": "notes.md"}]


REASON_SOURCES = ("engine/tls/pair.py", "engine/coreg/coregister.py", "engine/tls/scanner_position.py")


def _words(text: str) -> list[str]:
    """The literal words of a reason: placeholders (``{...}`` in the code, a lone capital such as
    ``N`` or ``X`` in the docs) and punctuation left out."""
    text = re.sub(r"\{[^}]*\}", " ", text)
    return [w.lower() for w in re.findall(r"[A-Za-z%][A-Za-z0-9%'-]*", text.replace("`", " "))]


def test_troubleshooting_explains_every_failure_reason():
    """Every reason a registration or co-registration fails with, as the code words it, is
    explained on the troubleshooting page (matched on its first literal words)."""
    page = " ".join(
        _words(
            re.sub(
                r"(?<![A-Za-z])[A-Z](?![A-Za-z])",
                " ",
                (ROOT / "docs" / "troubleshooting.md").read_text(encoding="utf-8"),
            )
        )
    )
    pattern = re.compile(
        r'(?:\b(?:_failed|failed|CoarseAttempt)\(\s*(?:[^"\n()]*,\s*)?|\bproblem\s*=\s*\(?\s*)f?"([^"\n]{8,})"'
    )
    missing, checked = [], 0
    for source in REASON_SOURCES:
        for m in pattern.finditer((ROOT / source).read_text(encoding="utf-8")):
            words = _words(m.group(1))
            if len(words) < 3:  # a wrapper such as "UAV cloud: {exc}" around another reason
                continue
            checked += 1
            if " ".join(words[:3]) not in page:
                missing.append(f"{source}: {m.group(1)[:80]}")
    assert checked >= 15  # the reasons were found in the code
    assert missing == [], "failure reasons not explained in docs/troubleshooting.md"
