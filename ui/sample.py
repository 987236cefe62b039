"""The sample plot behind "Open sample plot": three simulated scans of a mixed temperate forest,
made by the engine's simulator on first use into the user's data folder and reused after."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Optional

from ..app.plot import Project
from ..engine.core.errors import Cancelled
from ..engine.core.progress import CancelToken
from ..engine.tls.params import RegistrationParams

PRESET = "mixed_temperate"
POSITIONS = [(0.0, 0.0), (10.0, 2.0), (-8.0, 6.0)]
SEED = 7
STEP_DEG = 0.3
SIZE_M = 40.0
PROJECT_FILE = "sample_plot.forestreg.json"


def sample_dir() -> Path:
    """Where the sample lives: ``$FORESTREG_SAMPLE_DIR``, else the platform's user data folder."""
    env = os.environ.get("FORESTREG_SAMPLE_DIR")
    if env:
        return Path(env)
    from PySide6.QtCore import QStandardPaths

    base = QStandardPaths.writableLocation(QStandardPaths.StandardLocation.GenericDataLocation)
    return Path(base or Path.home()) / "forestreg" / "sample_plot"


def make_sample_project(
    folder: Optional[Path] = None,
    progress: Optional[Callable[[float, str], None]] = None,
    cancel: Optional[CancelToken] = None,
) -> Path:
    """The sample project's file, simulating the scans first when they are not there yet."""
    folder = Path(folder or sample_dir())
    path = folder / PROJECT_FILE
    if path.is_file():
        return path
    from ..app.simulation import simulate_files

    folder.mkdir(parents=True, exist_ok=True)

    def report(fraction: float, message: str) -> None:
        if cancel is not None and cancel.cancelled:
            raise Cancelled("cancelled by the user")
        if progress is not None:
            progress(0.95 * fraction, f"simulating the sample plot: {message}")

    files = simulate_files(PRESET, POSITIONS, folder, seed=SEED, step_deg=STEP_DEG, size_m=SIZE_M, progress=report)
    # the angular step of the search matches the simulated scanner's resolution (faster, same result)
    project = Project(name="sample plot (simulated)", params=RegistrationParams(angular_step_deg=STEP_DEG))
    for f in files:
        project.add_scan(f)
    project.save(path)
    if progress is not None:
        progress(1.0, "sample plot ready")
    return path
