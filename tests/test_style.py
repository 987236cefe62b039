"""The code style is checked, not assumed: ``ruff check`` (pyflakes, pycodestyle errors and
warnings, sorted imports) and ``ruff format --check`` pass on the whole repository, with the
settings of ``pyproject.toml`` (``[tool.ruff]``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _ruff(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ruff", *args], cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_ruff_check_passes():
    run = _ruff("check", "--no-cache", ".")
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]


def test_ruff_format_leaves_every_file_as_it_is():
    run = _ruff("format", "--check", "--no-cache", ".")
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]


def test_the_style_settings_hold_the_line_length():
    """The formatter's line length is the one the code was formatted at; lines longer than it
    are strings and comments the formatter does not break."""
    import tomllib

    ruff = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ruff"]
    assert ruff["line-length"] == 120
    assert {"F", "E9", "I"} <= set(ruff["lint"]["select"])
