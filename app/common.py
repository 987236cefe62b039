"""What every use case shares: the files' units, the typed outcome of a run, progress with
cancellation, the last check before a result is called "ok", and the checks of what the Python API
is given (clouds as scans, arrays or files; parameters; plot projects)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from ..engine.core.errors import InvalidArgumentError, ParameterError, ScanDataError, UsageError
from ..engine.core.outcome import Outcome
from .units import UNITS, crs_unit_problem, precision_problem, unit_of_scale, unit_problem  # noqa: F401 - metres per unit of the files' coordinates

ProgressCallback = Callable[[float, str], None]


@dataclass(frozen=True, eq=False)
class RunOutcome(Outcome):
    """The outcome of one use case: ``status`` ("ok" or "failed"), ``reason``, ``matrix`` (4x4 in
    the files' unit, or None), ``timings`` (seconds per step), the output folder or file ``out``
    (None when nothing was written), ``summary`` (the ``result.json`` written, or the figures of
    the run) and ``result`` (the engine's typed result). Falsy when not ok.

    ``result_file`` and ``outputs``: the file a program reads first (``poses.json``, ...) and every
    file or folder the run wrote, as absolute paths, when the use case lists them (the command
    line hands them to the job service and the batch in its ``end`` event: nothing is guessed from
    file names)."""

    status: str
    reason: str = ""
    matrix: Optional[np.ndarray] = None
    timings: dict = field(default_factory=dict)
    out: Optional[Path] = None
    summary: dict = field(default_factory=dict)
    result: Any = None
    result_file: Optional[Path] = None
    outputs: tuple = ()

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


def rigid_or_withheld(result):
    """The last check of a typed registration result (``status``, ``reason``, ``matrix``; a frozen
    dataclass such as :class:`~forestreg.engine.tls.pair.PairResult`) before the Python API returns
    it "ok": the check of :func:`final_result_check`. A matrix that is not a finite proper rigid
    4x4 gives a copy "failed" with the reason and no matrix; anything else is returned as it is."""
    import dataclasses

    from ..engine.core.errors import TransformError
    from ..engine.core.transform import check_rigid

    if getattr(result, "status", None) != "ok":
        return result
    try:
        check_rigid(result.matrix, "the result")
    except TransformError as exc:
        return dataclasses.replace(result, status="failed", reason=f"{exc}; withheld", matrix=None)
    return result


def run_summary(
    result,
    read: dict,
    inputs: dict,
    units: str,
    scale: float,
    *,
    facts: Optional[dict] = None,
    matrix_keys: tuple[str, ...] = ("matrix",),
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
    return cls(
        status=str(summary.get("status") or "failed"),
        reason=str(summary.get("reason") or ""),
        matrix=None if m is None else np.asarray(m, dtype=float),
        timings=dict(summary.get("timings") or {}),
        out=out,
        summary=summary,
        result=result,
        **extra,
    )


def check_inputs_exist(*paths) -> None:
    """Every input file exists and is a readable file (one line otherwise, before any work)."""
    from ..engine.io.base import check_readable

    for p in paths:
        if p is not None:
            check_readable(p)


def same_file(a, b) -> bool:
    """Whether paths ``a`` and ``b`` name one file (links and ``..`` resolved; False when either
    cannot be looked at)."""
    import os

    try:
        return Path(a).resolve() == Path(b).resolve() or os.path.samefile(a, b)
    except OSError:
        return False


def refuse_same_file(a, b, message: str) -> None:
    """A :class:`~forestreg.engine.core.errors.UsageError` (exit 2) saying ``message`` (with the
    file named) when ``a`` and ``b`` are one file: a command comparing two inputs given one twice
    would report a perfect, meaningless match."""
    if a is not None and b is not None and same_file(a, b):
        raise UsageError(f"{message} ({a})")


class UnitError(UsageError, ScanDataError):
    """A cloud's coordinates are not in the unit given (``--units``, or metres for the Python API):
    raised by :func:`check_units` with the likely unit. A
    :class:`~forestreg.engine.core.errors.UsageError` (exit 2) and a
    :class:`~forestreg.engine.core.errors.ScanDataError` (the points are unusable as given)."""


def check_units(cloud, units: str = "m", label: str = "cloud") -> None:
    """Refuse a cloud whose coordinates are not in ``units``: :class:`UnitError` naming the likely
    unit and how to give it. ``cloud`` is a :class:`~forestreg.engine.core.scan.Scan` or its points
    ((N, 3), already scaled to metres by ``units``). A scan whose file declares a CRS is refused
    when the CRS's unit is not the one the file was read in (its ``meta["unit_scale"]``) or is not
    one length on x, y and z
    (:func:`~forestreg.app.units.crs_unit_problem`); the points themselves are judged by their
    extent and spacing (:func:`~forestreg.app.units.unit_problem`) and their precision
    (:func:`~forestreg.app.units.precision_problem`). The one unit check of every command that
    reads a cloud and of every function of the Python API that takes one; well under a second."""
    if units not in UNITS:
        raise UsageError(f"unknown unit {units!r}: one of {', '.join(UNITS)}")
    points = getattr(cloud, "points", cloud)
    meta = getattr(cloud, "meta", None)
    crs, read_in = None, units
    if isinstance(meta, dict):  # the CRS is judged against the unit the file was read in
        crs, read_in = meta.get("crs"), unit_of_scale(meta.get("unit_scale", UNITS[units]))
    problem = (
        crs_unit_problem(crs, read_in, label) or unit_problem(points, units, label) or precision_problem(points, label)
    )
    if problem:
        raise UnitError(problem)


def refuse_scans_given_twice(paths) -> None:
    """:class:`~forestreg.engine.core.errors.UsageError` (exit 2) naming the scans given more
    than once among ``paths`` (compared as resolved paths: links and ``..`` followed)."""
    resolved = [Path(p).resolve() for p in paths]
    twice = sorted({str(p) for p, r in zip(paths, resolved) if resolved.count(r) > 1})
    if twice:
        raise UsageError(f"a scan is given twice: {', '.join(twice)}")


def given_crs(crs, units: str = "m"):
    """The CRS a user gave (``--crs``: a :class:`~forestreg.engine.io.crs.Crs`, text such as
    "EPSG:32618" or a WKT, or None) for coordinates read in ``units``, refused as a file's own CRS
    would be (:func:`~forestreg.app.units.crs_unit_problem`, :class:`UnitError`): a geographic or
    geocentric CRS, one in another unit, one mixing units."""
    from ..engine.io.crs import as_crs

    found = as_crs(crs, "--crs")
    problem = crs_unit_problem(found, units, "--crs")
    if problem:
        raise UnitError(problem)
    return found


def check_upright(cloud, label: str = "cloud") -> None:
    """Refuse a cloud whose z axis is not up (:class:`~forestreg.engine.core.errors.UsageError`,
    exit 2): its trunks stand clearly off z (:func:`~forestreg.engine.tls.level.stem_axis`; a
    scan in a tilted scanner's own frame, or a cloud exported on its side), where stems, heights
    and crowns would be measured across the trees. ``cloud``: a Scan or its (N, 3) points,
    metres. About half a second; a cloud without clear trunks passes."""
    from ..engine.tls.level import stem_axis

    axis = stem_axis(getattr(cloud, "points", cloud))
    if not axis.upright:
        raise UsageError(
            f"{label}: its z axis is not up: its trunks stand along a direction {axis.tilt_deg:.0f} deg off it "
            "(a scan in a tilted scanner's own frame, or a cloud exported on its side); level it first "
            "(register a tilted scan onto a level one with `forestreg register` or `plot`)"
        )


def check_near_scanner(scan, max_range_m: float, path, units: str, *, units_checked: bool = False) -> None:
    """Refuse, before the work, a scan whose coordinates are not in ``units``
    (:func:`check_units`) or with hardly any points within ``D_c`` of its
    scanner: a georeferenced scan without ``--scanner-position`` or a file in another unit than
    ``--units`` (``units_checked``: the unit was checked when the scan was read)."""
    from ..engine.geometry.voxel import column_bounds
    from ..engine.tls.scanner_position import points_within

    if not units_checked:
        check_units(scan, units, str(path))
    lo, hi = column_bounds(scan.points)
    span = max(float(hi[0] - lo[0]), float(hi[1] - lo[1]))
    if span < 2.0:
        raise UsageError(
            f"{path}: with --units {units} the points span only {span:.2f} m horizontally; a forest scan spans tens of metres: "
            "check the file's unit (--units)"
        )
    near = points_within(scan.points, scan.scanner_position, max_range_m)
    if near < 1000 or near < 0.01 * len(scan.points):
        pos = ", ".join(f"{v:.2f}" for v in scan.scanner_position_file / UNITS[units])
        raise UsageError(
            f"{path}: only {near} of {len(scan.points)} points lie within D_c = {max_range_m:g} m of the scanner position ({pos} {units}); "
            "for a georeferenced scan give --scanner-position X,Y,Z, and check the file's unit (--units cm|mm|ft)"
        )


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


# ----------------------------------------------------------------------------- the Python API's inputs

#: What a cloud given to the Python API may be, for messages.
CLOUD_TYPES = "a Scan (forestreg.read_scan), an (N, 3) array of x, y, z in metres, or a point file's path"


def as_scan(cloud, what: str = "cloud", *, units: bool = True):
    """A checked :class:`~forestreg.engine.core.scan.Scan` from what the Python API was given: a
    scan, an (N, 3) array (or nested sequence) of finite x, y, z in metres, or the path of a point
    file (read in metres). Its coordinates must be in metres (:func:`check_units`,
    unless ``units`` is False). Anything else raises the product's error naming what is expected:
    :class:`~forestreg.engine.core.errors.InvalidArgumentError` (another type),
    :class:`~forestreg.engine.core.errors.ScanDataError` (not (N, 3), NaN, too few points),
    :class:`UnitError` (not metres), :class:`~forestreg.engine.core.errors.ScanReadError` (a file
    that cannot be read)."""
    import os

    from ..engine.core.scan import Scan

    if isinstance(cloud, Scan):
        scan = cloud
    elif isinstance(cloud, (str, os.PathLike)):
        from ..engine.io import read_scan as read

        scan = read(cloud)
    else:
        scan = Scan.from_points(as_points(cloud, what, min_points=10), name=what)
    if units:
        check_units(scan, "m", what if what != "cloud" or not scan.name else scan.name)
    return scan


def as_points(points, what: str = "points", *, min_points: int = 1) -> np.ndarray:
    """``points`` as a float64 (N, 3) array of finite x, y, z, or the product's error saying what
    is wrong (:class:`~forestreg.engine.core.errors.InvalidArgumentError` for another type,
    :class:`~forestreg.engine.core.errors.ScanDataError` for the shape, NaN or too few points)."""
    from ..engine.core.scan import Scan, check_points

    if isinstance(points, Scan):
        return points.points
    if isinstance(points, (str, bytes, dict)) or points is None or not hasattr(points, "__len__"):
        raise InvalidArgumentError(f"{what}: expected {CLOUD_TYPES}, got {type(points).__name__}")
    try:
        return check_points(points, what, min_points=min_points)
    except (TypeError, ValueError) as exc:  # not numbers, or ragged
        raise InvalidArgumentError(
            f"{what}: expected an (N, 3) array of numbers (x, y, z in metres), got {type(points).__name__} "
            f"that is not one ({exc})"
        ) from exc


def scan_source(source, what: str):
    """What the engine's registrations take for a scan: a checked scan (:func:`as_scan`), or, for a
    function that reads one (``lambda: read_scan(path)``), a function that reads and checks it."""
    if callable(source) and not isinstance(source, type):

        def load():
            return as_scan(source(), what)

        return load
    return as_scan(source, what)


def params_of(params, cls, section: str):
    """``params`` as a ``cls`` (the defaults for None; the ``section`` of a
    :class:`~forestreg.engine.params.ProductParams`), or a
    :class:`~forestreg.engine.core.errors.ParameterError` naming the type expected."""
    if params is None:
        return cls()
    if isinstance(params, cls):
        return params
    from ..engine.params import ProductParams

    if isinstance(params, ProductParams) and section:
        return getattr(params, section)
    raise ParameterError(f"params: expected a {cls.__name__} (or a ProductParams), got {type(params).__name__}")


def read_scan(path, **options):
    """:func:`forestreg.engine.io.read_scan` (same arguments), and the scan's coordinates checked to
    be in metres once ``unit_scale`` is applied (:func:`check_units`: a file
    in cm or mm read without its ``unit_scale`` raises :class:`UnitError` naming the likely one)."""
    import os

    from ..engine.io import read_scan as read

    if not isinstance(path, (str, os.PathLike)):
        raise InvalidArgumentError(
            f"expected the path of a point file (str or pathlib.Path), got {type(path).__name__}"
        )
    scan = read(path, **options)
    check_units(scan, unit_of_scale(options.get("unit_scale", 1.0)), str(path))
    return scan


def read_scans(path, **options):
    """:func:`forestreg.engine.io.read_scans` (same arguments: every scan of an E57 file), each
    scan's coordinates checked to be in metres once ``unit_scale`` is applied."""
    import os

    from ..engine.io import read_scans as read

    if not isinstance(path, (str, os.PathLike)):
        raise InvalidArgumentError(
            f"expected the path of a point file (str or pathlib.Path), got {type(path).__name__}"
        )
    scans = read(path, **options)
    for scan in scans:
        check_units(scan, unit_of_scale(options.get("unit_scale", 1.0)), f"{path} ({scan.name})")
    return scans


def write_scan(scan, path, *, matrix=None) -> None:
    """:func:`forestreg.engine.io.write_scan`: a scan (or an (N, 3) array of x, y, z in metres)
    written to ``path`` (format from the suffix), optionally moved by ``matrix``."""
    from ..engine.io import write_scan as write

    write(as_scan(scan, "scan", units=False), path, matrix=matrix)


# ----------------------------------------------------------------------------- plot projects (Python API)


def _as_project(project, what: str = "project"):
    from ..engine.tls.project import Project

    if isinstance(project, Project):
        return project
    if isinstance(project, (str, Path)):
        return Project.load(project)
    raise InvalidArgumentError(
        f"{what}: expected a Project (forestreg.Project.load(path)) or a project file's path, "
        f"got {type(project).__name__}"
    )


def checked_scans(project, scans=None, *, with_intensity: bool = True):
    """The plot's scans (a :class:`~forestreg.engine.tls.plot.ScanCache`, ``scans`` when given),
    checked before the work (the ``plot`` command's check, and the Python API's): each scan in
    turn until one has its coordinates in metres and points near its scanner
    (:func:`check_near_scanner`); when none has, the first one's problem is raised in one line
    (:class:`UnitError`, :class:`~forestreg.engine.core.errors.UsageError` or
    :class:`~forestreg.engine.core.errors.ScanDataError`: exit 2) instead of every link failing
    after minutes. A single such scan fails its own link; an unreadable one too."""
    from ..engine.core.errors import ScanReadError
    from ..engine.tls.plot import ScanCache
    from ..engine.tls.scanner_position import ScannerPositionError

    if scans is None:
        scans = ScanCache(project, with_intensity=with_intensity)
    problems = []
    for s in project.scans:
        try:
            check_near_scanner(scans(s.name), project.params.max_range_m, s.path, "m")
        except ScannerPositionError as exc:  # the scanner is looked for as the scan is read: a file in cm shows none
            problems.append(_unit_error_of(s) or exc)
            continue
        except (UsageError, ScanDataError) as exc:  # the wrong unit, no points near the scanner, unusable points
            problems.append(exc)
            continue
        except ScanReadError:
            pass  # unreadable: its link reports it
        break
    if problems and len(problems) == len(project.scans):
        raise problems[0]
    return scans


def _unit_error_of(entry) -> Optional[Exception]:
    """The :class:`UnitError` of a project's scan (read again as it is), or None."""
    from ..engine.io import read_scan as read

    try:
        scan = read(entry.path, scan_index=entry.scan_index, with_intensity=False)
        check_units(scan, "m", str(entry.path))
    except UnitError as exc:
        return exc
    except Exception:  # noqa: BLE001 - any other problem is the one already found
        return None
    return None


def register_project(project, *, scans=None, **options):
    """:func:`forestreg.engine.tls.plot.register_project` (same options) of a checked project: a
    :class:`~forestreg.engine.tls.project.Project` (or its file) whose scans are in metres. A
    project with a file is saved to it after each finished link and at the end
    (:func:`~forestreg.engine.io.results.save_to_its_file`; ``on_link_done`` replaces that)."""
    from ..engine.io.results import save_to_its_file
    from ..engine.tls.plot import register_project as register

    project = _as_project(project)
    done = options.setdefault("on_link_done", save_to_its_file)
    outcome = register(project, scans=checked_scans(project, scans, with_intensity=False), **options)
    if done is not None:
        done(project)
    return outcome


def register_survey(project, params=None, *, scans=None, **options):
    """:func:`forestreg.engine.tls.survey.register_survey` (same options) of a checked project
    (see :func:`register_project`, saved the same way, the adjustment with it); ``params`` a
    :class:`~forestreg.engine.tls.survey.SurveyParams`."""
    from ..engine.io.results import save_to_its_file
    from ..engine.tls.survey import SurveyParams
    from ..engine.tls.survey import register_survey as register

    project = _as_project(project)
    done = options.setdefault("on_link_done", save_to_its_file)
    outcome = register(
        project,
        params_of(params, SurveyParams, "survey"),
        scans=checked_scans(project, scans, with_intensity=False),
        **options,
    )
    if done is not None:
        done(project)
    return outcome


def compare_auto_manual(project, *, scans=None, **options):
    """:func:`forestreg.engine.tls.compare.compare_auto_manual` (same options) of a checked project
    (see :func:`register_project`, saved the same way after each automatic link)."""
    from ..engine.io.results import save_to_its_file
    from ..engine.tls.compare import compare_auto_manual as compare

    project = _as_project(project)
    options.setdefault("on_link_done", save_to_its_file)
    return compare(project, scans=checked_scans(project, scans, with_intensity=False), **options)


def release_output_locks() -> list[str]:
    """Release every output-folder lock this process holds (a long-lived process, the desktop or
    a Python session, once no run of its own is writing): a run that failed between checking its
    output folder and writing it keeps no other process out of that folder. Returns the folders
    released."""
    from ..engine.core.atomic import held_output_locks, release_output_folder

    held = held_output_locks()
    for folder in held:
        release_output_folder(folder)
    return held
