"""Distribution: ``python -m build`` makes a wheel and a source archive with the package's version;
the wheel installs into a new virtual environment outside the checkout (no system site packages,
no path into the checkout), where ``forestreg --version`` answers and a small simulated pair
registers to the simulator's truth.

The environment is made with ``uv`` where it is installed (the ``test`` extra brings it): it
installs the wheel and its dependencies from PyPI through its cache, linking the cached files
instead of unpacking 1.7 GB again, so a repeated run takes seconds; without ``uv``, ``venv`` and
``pip`` do the same more slowly."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def _version() -> str:
    import forestreg

    return forestreg.__version__


def _clean_env() -> dict:
    """The environment without anything that points into the checkout or another environment."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP")}
    env["PYTHONNOUSERSITE"] = "1"
    return env


def _base_python() -> str:
    """The interpreter this test's environment was made from (not the environment itself)."""
    for candidate in (getattr(sys, "_base_executable", ""), os.path.join(sys.base_prefix, "bin", "python3")):
        if candidate and Path(candidate).exists() and Path(candidate).resolve() != Path(sys.executable).resolve():
            return candidate
    return os.path.join(sys.base_prefix, "bin", "python3")


def _uv() -> list[str] | None:
    found = shutil.which("uv") or (
        str(Path(sys.executable).with_name("uv")) if Path(sys.executable).with_name("uv").exists() else None
    )
    return [found] if found else None


@pytest.fixture(scope="module")
def dist(tmp_path_factory) -> Path:
    pytest.importorskip("build", reason="the 'build' package is not installed (pip install -e '.[test]')")
    out = tmp_path_factory.mktemp("dist")
    run = subprocess.run(
        [sys.executable, "-m", "build", "--outdir", str(out), str(ROOT)], capture_output=True, text=True, timeout=900
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return out


def test_build_makes_a_wheel_and_an_sdist_with_the_version(dist):
    version = _version()
    wheel = dist / f"forestreg-{version}-py3-none-any.whl"
    sdist = dist / f"forestreg-{version}.tar.gz"
    assert wheel.is_file() and sdist.is_file(), sorted(p.name for p in dist.iterdir())
    names = set(zipfile.ZipFile(wheel).namelist())
    for needed in (
        "forestreg/__init__.py",
        "forestreg/metadata.txt",
        "forestreg/cli/__init__.py",
        "forestreg/engine/tls/pair.py",
        "forestreg/resources/default_params.toml",
        "forestreg/resources/icons/run.svg",
        "forestreg/plugin/qgis/provider.py",
    ):
        assert needed in names, needed
    assert not any(
        n.startswith(("forestreg/tests/", "tests/", "forestreg/docs/", "forestreg/scripts/", "forestreg/benchmarks/"))
        for n in names
    )
    archive = tarfile.open(sdist).getnames()
    for needed in (
        "CHANGELOG.md",
        "README.md",
        "mkdocs.yml",
        "docs/index.md",
        "scripts/docs_hooks.py",
        "scripts/package_qgis.py",
        "tests/test_docs.py",
    ):
        assert f"forestreg-{version}/{needed}" in archive, needed
    meta = zipfile.ZipFile(wheel).read(f"forestreg-{version}.dist-info/METADATA").decode()
    assert f"Version: {version}" in meta
    entry = zipfile.ZipFile(wheel).read(f"forestreg-{version}.dist-info/entry_points.txt").decode()
    assert "forestreg = forestreg.cli:entry" in entry and "cloudcompare.plugins" in entry


def test_the_wheel_installs_and_registers_in_a_clean_environment(dist, tmp_path):
    version = _version()
    wheel = dist / f"forestreg-{version}-py3-none-any.whl"
    venv = tmp_path / "venv"
    env = _clean_env()
    uv = _uv()
    if uv:
        subprocess.run(
            uv + ["venv", "-q", "-p", _base_python(), str(venv)], check=True, env=env, cwd=tmp_path, timeout=300
        )
        install = uv + ["pip", "install", "-q", "-p", str(venv / "bin" / "python"), str(wheel)]
    else:
        subprocess.run([_base_python(), "-m", "venv", str(venv)], check=True, env=env, cwd=tmp_path, timeout=300)
        install = [str(venv / "bin" / "python"), "-m", "pip", "install", "-q", str(wheel)]
    run = subprocess.run(install, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=1800)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    python = venv / "bin" / "python"
    # the environment is clean: no system site packages, and forestreg comes from the wheel
    where = subprocess.run(
        [
            str(python),
            "-c",
            "import sys, forestreg; print(forestreg.__file__); print(sys.flags.no_user_site, any('site-packages' in p and not p.startswith(sys.prefix) for p in sys.path))",
        ],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=120,
    )
    assert where.returncode == 0, where.stderr
    location, flags = where.stdout.split("\n", 1)
    assert Path(location).resolve().is_relative_to(venv.resolve()) and not Path(location).resolve().is_relative_to(ROOT)
    assert flags.split() == ["1", "False"]

    forestreg = str(venv / "bin" / "forestreg")
    out = subprocess.run([forestreg, "--version"], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == f"forestreg {version}", out.stdout + out.stderr

    sim = subprocess.run(
        [
            forestreg,
            "simulate",
            "planted_conifer",
            "--out",
            "sim",
            "--positions",
            "0,0;7,2",
            "--step",
            "0.5",
            "--size",
            "30",
            "-q",
        ],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=900,
    )
    assert sim.returncode == 0, sim.stderr[-3000:]
    reg = subprocess.run(
        [forestreg, "register", "sim/scan_01.laz", "sim/scan_02.laz", "--out", "pair", "-q"],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=900,
    )
    assert reg.returncode == 0, reg.stdout[-2000:] + reg.stderr[-3000:]
    result = json.loads((tmp_path / "pair" / "result.json").read_text())
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    poses = {s["name"]: np.array(s["matrix"]) for s in truth["scans"]}
    expected = np.linalg.inv(poses["scan_01"]) @ poses["scan_02"]
    error = np.linalg.inv(expected) @ np.array(result["matrix"])
    angle = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
    assert result["status"] == "ok" and angle < 0.05 and np.linalg.norm(error[:3, 3]) < 0.02, (angle, error[:3, 3])
