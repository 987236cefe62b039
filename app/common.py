"""What every use case shares: the files' units, the typed outcome of a run, progress with
cancellation, and the last check before a result is called "ok"."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from ..engine.core.outcome import Outcome

from .units import UNITS  # noqa: F401 - metres per unit of the files' coordinates

ProgressCallback = Callable[[float, str], None]


@dataclass(frozen=True, eq=False)
class RunOutcome(Outcome):
    """The outcome of one use case: ``status`` ("ok" or "failed"), ``reason``, ``matrix`` (4x4 in
    the files' unit, or None), ``timings`` (seconds per step), the output folder or file ``out``
    (None when nothing was written), ``summary`` (the ``result.json`` written, or the figures of
    the run) and ``result`` (the engine's typed result). Falsy when not ok."""

    status: str
    reason: str = ""
    matrix: Optional[np.ndarray] = None
    timings: dict = field(default_factory=dict)
    out: Optional[Path] = None
    summary: dict = field(default_factory=dict)
    result: Any = None

    def evidence(self) -> dict[str, Any]:
        ev = self.summary.get("evidence") if isinstance(self.summary, dict) else None
        return dict(ev) if isinstance(ev, dict) else {}

    def to_dict(self) -> dict[str, Any]:
        return dict(self.summary) if self.summary else self.outcome_dict()


def with_cancel(progress: Optional[ProgressCallback], cancel=None) -> Optional[ProgressCallback]:
    """``progress`` that first checks ``cancel`` (a :class:`~forestreg.engine.core.progress.
    CancelToken`): the engine calls it between steps, so a cancel stops the run at the next step."""
    if cancel is None:
        return progress

    def report(fraction: float, message: str = "") -> None:
        cancel.raise_if_cancelled()
        if progress is not None:
            progress(fraction, message)

    return report


def final_result_check(summary: dict) -> dict:
    """The last check before a result is called "ok" (see
    :func:`~forestreg.engine.core.transform.withhold_unless_rigid`)."""
    from ..engine.core.transform import withhold_unless_rigid

    return withhold_unless_rigid(summary)


def run_summary(
    result, read: dict, inputs: dict, units: str, scale: float, *,
    facts: Optional[dict] = None, matrix_keys: tuple[str, ...] = ("matrix",),
) -> tuple[dict, bool]:
    """The ``result.json`` summary of a registration-like ``result`` and whether it is "ok".

    ``read`` (read times) goes in front of the result's own timings; ``inputs`` (key -> input
    file) follow as absolute paths, then ``facts``, then the unit; the matrices named by
    ``matrix_keys`` are turned into the files' unit."""
    from ..engine.core.transform import to_file_units

    summary = final_result_check(result.to_dict())
    ok = summary["status"] == "ok"
    summary["timings"] = {**read, **summary["timings"]}
    summary.update({key: str(Path(path).resolve()) for key, path in inputs.items()})
    summary.update(facts or {})
    summary["unit"] = units
    summary["unit_scale"] = scale
    for key in matrix_keys:
        if summary.get(key) is not None:
            summary[key] = to_file_units(np.asarray(summary[key]), scale).tolist()
    return summary, ok


def outcome_of(summary: dict, *, out: Optional[Path] = None, result: Any = None, cls=RunOutcome, **extra) -> RunOutcome:
    """A typed outcome from a checked ``result.json`` summary."""
    m = summary.get("matrix")
    return cls(status=str(summary.get("status") or "failed"), reason=str(summary.get("reason") or ""),
               matrix=None if m is None else np.asarray(m, dtype=float), timings=dict(summary.get("timings") or {}),
               out=out, summary=summary, result=result, **extra)


def check_inputs_exist(*paths) -> None:
    """Every input file exists and is a readable file (one line otherwise, before any work)."""
    from ..engine.io.base import check_readable

    for p in paths:
        if p is not None:
            check_readable(p)


def check_near_scanner(scan, max_range_m: float, path, units: str) -> None:
    """Refuse, before the work, a scan with hardly any points within ``D_c`` of its scanner: a
    georeferenced scan without ``--scanner-position`` or a file in another unit than ``--units``."""
    from ..engine.core.errors import UsageError
    from ..engine.geometry.voxel import column_bounds
    from ..engine.tls.scanner_position import points_within

    lo, hi = column_bounds(scan.points)
    span = max(float(hi[0] - lo[0]), float(hi[1] - lo[1]))
    if span < 2.0:
        raise UsageError(
            f"{path}: with --units {units} the points span only {span:.2f} m horizontally; a forest scan spans tens of metres: "
            "check the file's unit (--units)")
    near = points_within(scan.points, scan.scanner_position, max_range_m)
    if near < 1000 or near < 0.01 * len(scan.points):
        pos = ", ".join(f"{v:.2f}" for v in scan.scanner_position_file / UNITS[units])
        raise UsageError(
            f"{path}: only {near} of {len(scan.points)} points lie within D_c = {max_range_m:g} m of the scanner position ({pos} {units}); "
            "for a georeferenced scan give --scanner-position X,Y,Z, and check the file's unit (--units cm|mm|ft)")


def check_replaceable_point_file(path, dimension: str, what: str) -> None:
    """An existing point file at an output path is replaced only when it is an earlier output of
    the same kind (a LAS/LAZ with the extra ``dimension``); a user's own scan is refused."""
    from ..engine.core.errors import OutputPathError

    p = Path(path)
    if not p.exists():
        return
    if p.suffix.lower() in (".las", ".laz"):
        try:
            import laspy

            with laspy.open(p) as f:
                names = set(f.header.point_format.dimension_names)
            if dimension in names:
                return
        except Exception:  # unreadable: not ours either
            pass
    raise OutputPathError(f"{p} exists and is not an earlier {what}: it would be overwritten; give a new file name")


def import_in_background(*modules: str, kernels: bool | str = False) -> None:
    """Import ``modules`` (relative to the package, e.g. ``".engine.report.figures"``) in a daemon
    thread: a use case imports what it needs only at the end (matplotlib for the figure, ~0.3 s)
    while its compiled work runs. With ``kernels``, the thread first loads one compiled kernel
    (LLVM's start-up, ~0.3 s) while the inputs are read; with the name of a use case (e.g.
    ``"pair"``), then every kernel that use case loaded in its last run, in their order
    (:func:`~forestreg.engine.core.jit.preload`, ~40 ms each). An import that fails here fails
    again, with its message, where the module is used. A process allowed one core
    (:func:`~forestreg.engine.core.jit.worker_count`, e.g. a batch's ``--threads 1``) starts no
    such thread: the modules and kernels load where they are used, on that core."""
    import importlib
    import threading

    from ..engine.core.jit import worker_count

    if worker_count() <= 1:
        return

    def run() -> None:
        if kernels:
            try:
                from ..engine.geometry.voxel import warm_up

                warm_up()
                if isinstance(kernels, str):
                    from ..engine.core.jit import preload

                    preload(kernels)
            except Exception:  # the kernel is loaded (or its failure reported) where it is used
                pass
        for name in modules:
            try:
                importlib.import_module(name, __package__.rpartition(".")[0])
            except Exception:  # reported where the module is used
                pass

    threading.Thread(target=run, name="forestreg-imports", daemon=True).start()
