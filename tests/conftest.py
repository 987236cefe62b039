"""Shared fixtures: the real data folder and a cache of simulated plots (simulated once per run)."""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Optional

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
# The test process itself never talks to the X server pytest-xvfb starts: Qt draws offscreen and
# VTK renders through EGL. Only the subprocess that opens the interactive window uses the display.
# (An X client still connected when Xvfb stops at exit makes Xlib end the process with status 1.)
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def pytest_sessionfinish(session, exitstatus):
    """Close every 3D view and window while the virtual display still runs."""
    import gc
    import sys

    if "pyvista" in sys.modules:
        sys.modules["pyvista"].close_all()
    qtwidgets = sys.modules.get("PySide6.QtWidgets")
    if qtwidgets is not None and qtwidgets.QApplication.instance() is not None:
        for widget in qtwidgets.QApplication.topLevelWidgets():
            widget.close()
            widget.deleteLater()
        qtwidgets.QApplication.processEvents()
    gc.collect()


def pytest_collection_modifyitems(config, items):
    """Every test that reads the real clouds (the ``shared_data`` fixture) carries the ``realdata``
    mark, so ``-m realdata`` runs them and ``-m "not realdata"`` leaves them out."""
    for item in items:
        if "shared_data" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.realdata)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real clouds of ``../shared/data``.

    Where the folder is absent the test is skipped with the path in the reason, except under CI
    (``CI`` set) or ``FORESTREG_REQUIRE_DATA=1``, where a missing folder fails the test: the
    real-data checks must never vanish silently from a run that is supposed to have them.
    """
    if not SHARED_DATA.is_dir():
        message = f"real data folder {SHARED_DATA} is absent (put ../shared/data beside the repository)"
        if os.environ.get("CI") or os.environ.get("FORESTREG_REQUIRE_DATA") == "1":
            pytest.fail(message)
        pytest.skip(message)
    return SHARED_DATA


@pytest.fixture(scope="session")
def sim_plot():
    """``sim_plot(preset, positions, seed=..., step=..., size=..., tilted=...)``: a simulated plot,
    made once per test run for each distinct set of arguments (tests must not modify it)."""
    return _simulated_plot


@functools.lru_cache(maxsize=None)
def _simulated_plot(
    preset: str,
    positions: tuple[tuple[float, float], ...],
    *,
    seed: int = 0,
    step: float = 0.25,
    size: float = 50.0,
    tilted: Optional[tuple[tuple[int, float], ...]] = None,
):
    """A simulated plot, cached for the whole test run (tests must not modify it)."""
    from forestreg.engine.simulate import simulate_plot

    return simulate_plot(
        preset,
        list(positions),
        seed=seed,
        angular_step_deg=step,
        size_m=size,
        tilted=dict(tilted) if tilted else None,
    )


@pytest.fixture
def window(qtbot, tmp_path: Path):
    """The main window, shown, non-interactive (no dialogs), with its settings in ``tmp_path``;
    afterwards any run or task is cancelled and awaited."""
    from PySide6.QtCore import QSettings

    from forestreg.ui.main_window import MainWindow

    w = MainWindow(settings=QSettings(str(tmp_path / "settings.ini"), QSettings.Format.IniFormat), interactive=False)
    qtbot.addWidget(w)
    w.show()
    yield w
    w.cancel_run()
    w.tasks.cancel_all()
    qtbot.waitUntil(lambda: not w.busy, timeout=400_000)


@pytest.fixture
def open_project(qtbot, window):
    """``open_project(path)``: open a project file in the main window and wait until its scene is
    shown and nothing runs any more."""

    def _open(path: Path) -> None:
        with qtbot.waitSignal(window.sceneReady, timeout=60_000):
            assert window.open_project(path)
        qtbot.waitUntil(lambda: not window.busy, timeout=60_000)

    return _open


@pytest.fixture
def scans_project(tmp_path: Path):
    """``scans_project(folder, name, params)``: an unregistered project of the ``scan_*.laz`` files
    of ``folder`` (in name order), saved as ``plot.json`` in the test's own folder."""
    from forestreg.engine.tls.project import Project

    def _make(folder: Path, name: str, params) -> Path:
        project = Project(name=name, params=params)
        for f in sorted(Path(folder).glob("scan_*.laz")):
            project.add_scan(f)
        return project.save(tmp_path / "plot.json")

    return _make
