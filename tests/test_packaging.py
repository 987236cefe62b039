"""The house rules of the package: import names, a Qt-free engine, QGIS metadata."""

from __future__ import annotations

import configparser
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["engine", "ui", "plugin", "cli"])
def test_no_plain_top_level_modules_are_importable(name, tmp_path):
    code = f"import importlib.util, sys; sys.exit(0 if importlib.util.find_spec({name!r}) is None else 1)"
    assert subprocess.run([sys.executable, "-c", code], cwd=tmp_path).returncode == 0, f"a plain '{name}' module is installed"


def test_package_imports_as_forestreg(tmp_path):
    code = "import forestreg, forestreg.engine, forestreg.engine.tls.pair, forestreg.cli; print(forestreg.__version__)"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def test_importing_forestreg_loads_no_qt_and_no_engine(tmp_path):
    code = "import sys, forestreg; bad = [m for m in sys.modules if m.startswith(('PySide6', 'pyvista', 'open3d', 'forestreg.engine'))]; print(bad); sys.exit(1 if bad else 0)"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout


def test_engine_never_imports_a_gui_library():
    pattern = re.compile(r"^\s*(from|import)\s+(PySide6|PyQt5|PyQt6|qtpy|pyvista|pyvistaqt|qgis)\b", re.M)
    offenders = [str(p.relative_to(ROOT)) for p in (ROOT / "engine").rglob("*.py") if pattern.search(p.read_text())]
    assert offenders == []


def test_qgis_metadata_has_the_required_fields():
    meta = configparser.ConfigParser()
    meta.read(ROOT / "metadata.txt")
    for key in ("name", "qgisMinimumVersion", "description", "version", "author", "email", "about"):
        assert meta.get("general", key).strip(), key
