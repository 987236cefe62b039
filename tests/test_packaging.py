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
    assert subprocess.run([sys.executable, "-c", code], cwd=tmp_path).returncode == 0, (
        f"a plain '{name}' module is installed"
    )


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


def _version() -> str:
    import forestreg

    return forestreg.__version__


def test_versions_agree():
    """One version: the package's, pyproject's (dynamic, read from it), QGIS's metadata.txt and
    the newest entry of CHANGELOG.md."""
    meta = configparser.ConfigParser()
    meta.read(ROOT / "metadata.txt")
    assert meta.get("general", "version") == _version()
    assert 'dynamic = ["version"]' in (ROOT / "pyproject.toml").read_text()
    newest = re.search(r"^## (\S+)", (ROOT / "CHANGELOG.md").read_text(), re.M)
    assert newest and newest.group(1) == _version()


def test_every_package_folder_is_packaged():
    """Every folder of the package that holds modules is in pyproject's ``packages`` (else the
    wheel and the QGIS zip would leave it out)."""
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    skip = {"tests", "benchmarks", "scripts", "docs", "build", "dist", "site", ".venv", ".git", "demo_out", "bench_out"}
    found = set()
    for init in ROOT.rglob("__init__.py"):
        rel = init.parent.relative_to(ROOT)
        if rel.parts and (rel.parts[0] in skip or rel.parts[0].startswith(".") or rel.parts[0].endswith(".egg-info")):
            continue
        found.add(".".join(("forestreg",) + rel.parts))
    assert found - listed == set()


def test_qgis_zip_from_metadata(tmp_path):
    import zipfile

    run = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "package_qgis.py"), "--out", str(tmp_path)],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    path = tmp_path / f"forestreg-qgis-{_version()}.zip"
    names = zipfile.ZipFile(path).namelist()
    assert {n.split("/")[0] for n in names} == {"forestreg"}
    for needed in (
        "forestreg/metadata.txt",
        "forestreg/__init__.py",
        "forestreg/plugin/qgis/host.py",
        "forestreg/plugin/qgis/provider.py",
        "forestreg/plugin/adapter.py",
        "forestreg/client.py",
        "forestreg/cli/__init__.py",
        "forestreg/engine/tls/pair.py",
        "forestreg/resources/icons/forestreg.svg",
    ):
        assert needed in names, needed
    assert not [n for n in names if n.endswith((".pyc", ".pyo")) or "/tests/" in n or "__pycache__" in n]
    meta = configparser.ConfigParser()
    meta.read_string(zipfile.ZipFile(path).read("forestreg/metadata.txt").decode())
    assert meta.get("general", "version") == _version()
    assert "def classFactory" in zipfile.ZipFile(path).read("forestreg/__init__.py").decode()


def test_qgis_zip_refuses_a_metadata_version_that_is_not_the_package_version(tmp_path):
    import shutil

    copy = tmp_path / "src"
    shutil.copytree(
        ROOT,
        copy,
        ignore=shutil.ignore_patterns(
            ".git", ".venv", "tests", "benchmarks", "docs", "__pycache__", "build", "dist", "site"
        ),
    )
    text = (copy / "metadata.txt").read_text().replace(f"version={_version()}", "version=0.0.1")
    (copy / "metadata.txt").write_text(text)
    run = subprocess.run(
        [sys.executable, str(copy / "scripts" / "package_qgis.py"), "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and "version 0.0.1" in run.stderr
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())
