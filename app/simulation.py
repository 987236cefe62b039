"""Simulation: TLS scans of a synthetic forest plot with known poses (``forestreg simulate``), and
the demo's cases with their truth (a TLS pair; a plot seen from the ground and from a UAV, with
field records).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from .common import RunOutcome, with_cancel


@dataclass(frozen=True, eq=False)
class SimulationOutcome(RunOutcome):
    """Simulated scans written to ``out`` (``scan_XX.laz`` + ``truth.json``): ``result`` is the
    engine's simulated plot; ``scans`` (name, points) per scan."""

    method = "simulated"
    scans: tuple = ()


def simulate_scans(
    preset: str,
    positions: Sequence,
    out,
    *,
    seed: int = 0,
    step_deg: float = 0.2,
    tilted: Optional[dict] = None,
    size_m: float = 60.0,
    progress=None,
    cancel=None,
) -> SimulationOutcome:
    """Simulate a plot of ``preset`` scanned from ``positions`` (x, y in metres; ``tilted`` index
    -> degrees) and write the folder ``out`` as a transaction."""
    from ..engine.core.atomic import check_output_folder, output_folder
    from ..engine.io.simulated import write_simulated_plot
    from ..engine.simulate import simulate_plot

    out = check_output_folder(out, "simulate")
    with output_folder(out, "simulate") as tmp:
        plot = write_simulated_plot(
            simulate_plot(
                preset,
                list(positions),
                seed=seed,
                angular_step_deg=step_deg,
                tilted=tilted or None,
                size_m=size_m,
                progress=with_cancel(progress, cancel),
            ),
            tmp,
        )
    files = tuple((out / f.name).resolve() for f in plot.files) + ((out / "truth.json").resolve(),)
    return SimulationOutcome(
        status="ok",
        out=out,
        result=plot,
        scans=tuple((s.scan.name, len(s.scan)) for s in plot.scans),
        result_file=files[-1],
        outputs=files,
    )


@dataclass(frozen=True)
class PairCase:
    """A simulated TLS pair: the two scan files and the true ``p_reference = truth @ p_moving``."""

    reference: Path
    moving: Path
    truth: np.ndarray


def simulated_pair(folder: Path, preset: str, *, seed: int = 1, step_deg: float = 0.15) -> PairCase:
    """Two scans of a ``preset`` plot 12 m apart, written into ``folder``, with their true pose."""
    from ..engine.io.simulated import write_simulated_plot
    from ..engine.simulate import relative_pose, simulate_plot

    folder.mkdir(parents=True, exist_ok=True)
    plot = write_simulated_plot(
        simulate_plot(preset, [(0.0, 0.0), (12.0, 3.0)], seed=seed, angular_step_deg=step_deg, size_m=50.0), folder
    )
    names = [s.scan.name for s in plot.scans]
    return PairCase(folder / f"{names[0]}.laz", folder / f"{names[1]}.laz", relative_pose(plot, names[0], names[1]))


@dataclass(frozen=True)
class CoregistrationCase:
    """A simulated plot seen from the ground and by a UAV: the two clouds, the field records
    (trees within 9 m of the centre) and the true ``p_uav = truth @ p_ground``."""

    ground: Path
    uav: Path
    field: Path
    truth: np.ndarray


def simulated_coregistration(
    folder: Path, *, seed: int = 1, size_m: float = 28.0, ground_extent_m: float = 18.0, tls_step_deg: float = 0.3
) -> CoregistrationCase:
    """A plot ``size_m`` across (28 m): merged TLS scans over ``ground_extent_m`` (ground-based, own
    frame, turned 120 deg and shifted 7 m) and a UAV flight at 86 m, written into ``folder`` with
    the field records."""
    from ..engine.core.atomic import write_text_atomic
    from ..engine.io import write_scan
    from ..engine.simulate.platforms import simulate_coregistration_case

    folder.mkdir(parents=True, exist_ok=True)
    case = simulate_coregistration_case(
        "planted_conifer",
        seed=seed,
        size_m=size_m,
        ground_platform="tls",
        ground_extent_m=ground_extent_m,
        heading_deg=120.0,
        offset_m=(5.0, -5.0, 1.0),
        uav_density_scale=0.5,
        tls_step_deg=tls_step_deg,
    )
    write_scan(case.ground, folder / "ground.laz")
    write_scan(case.uav, folder / "uav.laz")
    field = folder / "field.csv"
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["tree_id", "x", "y", "dbh_m", "height_m"])
    for t in case.scene.trees:
        if abs(t.x) < 9.0 and abs(t.y) < 9.0:
            w.writerow(
                [
                    f"T{t.id}",
                    f"{t.x + case.world_offset[0]:.3f}",
                    f"{t.y + case.world_offset[1]:.3f}",
                    f"{t.dbh_m:.4f}",
                    f"{t.height_m:.3f}",
                ]
            )
    write_text_atomic(field, buf.getvalue())
    return CoregistrationCase(folder / "ground.laz", folder / "uav.laz", field, np.asarray(case.matrix, dtype=float))


def errors_against(matrix: Any, truth: np.ndarray) -> tuple[float, float]:
    """Rotation (degrees) and translation (m) errors of ``matrix`` against ``truth``."""
    from ..engine.core.transform import rigid_errors

    return rigid_errors(np.asarray(matrix, dtype=float), truth)


def simulate_files(
    preset: str, positions: Sequence, folder: Path, *, seed: int, step_deg: float, size_m: float, progress=None
) -> list:
    """Simulate a plot into ``folder`` (no transaction: the desktop's sample); returns its scan files."""
    from ..engine.io.simulated import write_simulated_plot
    from ..engine.simulate import simulate_plot

    plot = write_simulated_plot(
        simulate_plot(preset, list(positions), seed=seed, angular_step_deg=step_deg, size_m=size_m, progress=progress),
        folder,
    )
    return list(plot.files)
