"""The QGIS zip of ``scripts/package_qgis.py``: readable by everyone (the zip and its files 0644,
its folders 0755, whatever the umask and the modes on disk), and refused with one line when
``metadata.txt`` lacks a field the QGIS plugin repository requires or recommends, or holds a
placeholder."""

from __future__ import annotations

import configparser
import importlib.util
import os
import shutil
import stat
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "package_qgis.py"


def _script():
    spec = importlib.util.spec_from_file_location("forestreg_package_qgis", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _shipped() -> dict[str, str]:
    meta = configparser.ConfigParser(interpolation=None)
    meta.read(ROOT / "metadata.txt", encoding="utf-8")
    return dict(meta["general"])


def _version() -> str:
    return _script().package_version(ROOT)


def _checkout_copy(tmp_path: Path) -> Path:
    """The files the script packages, copied (the script packages the folder it lies in)."""
    copy = tmp_path / "src"
    shutil.copytree(
        ROOT,
        copy,
        ignore=shutil.ignore_patterns(
            ".git",
            ".venv",
            "tests",
            "benchmarks",
            "docs",
            "__pycache__",
            "build",
            "dist",
            "site",
            "demo_out",
            "*.egg-info",
        ),
    )
    return copy


def _package(root: Path, out: Path, umask: int = 0o022) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(root / "scripts" / "package_qgis.py"), "--out", str(out)],
        capture_output=True,
        text=True,
        preexec_fn=lambda: os.umask(umask),
    )


def test_the_shipped_metadata_has_every_field_the_plugin_repository_asks_for():
    script = _script()
    meta = _shipped()
    assert script.metadata_problems(meta, _version()) == []
    for key in script.REQUIRED + script.RECOMMENDED:
        assert meta.get(key.lower(), "").strip(), key
    assert meta["repository"] == "https://github.com/forestreg/forestreg"
    assert meta["tracker"].startswith(meta["repository"])
    assert not meta["email"].endswith((".invalid", "example.com", "example.org"))


def test_the_zip_its_files_and_folders_are_readable_by_everyone(tmp_path):
    """Under a umask of 077, with a source file of mode 0600: the zip is 0644, every file entry
    0644 and every folder entry 0755 (each file's folders listed), as Unix entries."""
    root = _checkout_copy(tmp_path)
    (root / "client.py").chmod(0o600)
    out = tmp_path / "out"
    run = _package(root, out, umask=0o077)
    assert run.returncode == 0, run.stderr
    path = out / f"forestreg-qgis-{_version()}.zip"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert [p.name for p in out.iterdir()] == [path.name]  # no temporary file left
    with zipfile.ZipFile(path) as z:
        infos = z.infolist()
    names = {i.filename for i in infos}
    assert "forestreg/client.py" in names and "forestreg/metadata.txt" in names
    for info in infos:
        mode = info.external_attr >> 16
        assert info.create_system == 3, info.filename
        if info.is_dir():
            assert stat.S_ISDIR(mode) and stat.S_IMODE(mode) == 0o755, (info.filename, oct(mode))
        else:
            assert stat.S_ISREG(mode) and stat.S_IMODE(mode) == 0o644, (info.filename, oct(mode))
            parent = info.filename.rsplit("/", 1)[0] + "/"
            assert parent in names, f"{info.filename}: its folder has no entry"
    extracted = tmp_path / "plugins"
    with zipfile.ZipFile(path) as z:
        z.extractall(extracted)
        assert (extracted / "forestreg" / "client.py").read_bytes() == (root / "client.py").read_bytes()


@pytest.mark.parametrize(
    "change, words",
    [
        ({"repository": None}, ["repository", "required by the QGIS plugin repository"]),
        ({"email": None, "about": None}, ["lacks about, email, required"]),
        ({"tracker": None, "homepage": None}, ["tracker, homepage", "recommended"]),
        ({"tags": None}, ["tags", "recommended"]),
        ({"email": "forestreg@example.invalid"}, ["email", "placeholder"]),
        ({"email": "someone@example.com"}, ["placeholder"]),
        ({"email": "forestreg at github"}, ["not an e-mail address"]),
        ({"repository": "github.com/forestreg/forestreg"}, ["repository", "not a web address"]),
        ({"homepage": "https://example.org/forestreg"}, ["homepage", "placeholder"]),
        ({"qgisMinimumVersion": "three"}, ["qgisMinimumVersion", "not a version"]),
        ({"version": "0.0.1"}, ["version 0.0.1", "make them equal"]),
    ],
)
def test_metadata_problems_are_named(change, words):
    meta = {k: v for k, v in _shipped().items()}
    for key, value in change.items():
        meta.pop(key.lower(), None)
        if value is not None:
            meta[key.lower()] = value
    problems = "; ".join(_script().metadata_problems(meta, _version()))
    for word in words:
        assert word in problems, problems


def test_a_metadata_file_without_a_required_field_is_refused_in_one_line(tmp_path):
    root = _checkout_copy(tmp_path)
    lines = (root / "metadata.txt").read_text().splitlines()
    kept = [line for line in lines if not line.startswith(("repository=", "tracker="))]
    kept = [line.replace("forestreg@users.noreply.github.com", "forestreg@example.invalid") for line in kept]
    (root / "metadata.txt").write_text("\n".join(kept) + "\n")
    out = tmp_path / "out"
    run = _package(root, out)
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1, run.stderr
    for word in (
        "lacks repository, required",
        "lacks tracker, recommended",
        "email 'forestreg@example.invalid' is a placeholder",
    ):
        assert word in run.stderr, run.stderr
    assert not out.exists() or not list(out.iterdir())


def test_the_plugin_folder_ships_the_processing_model():
    """The register plot -> trees -> change model lies in a subfolder of the plugin package: the
    zip and the wheel carry it."""
    assert Path("plugin/models/plot_trees_change.model3") in _script().plugin_files(ROOT)
