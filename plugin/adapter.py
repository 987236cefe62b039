"""What the plugin hosts (QGIS, CloudCompare) share, without any host or Qt import.

The hosts never run the engine in their own process: they are thin clients of the forestreg job
service (``forestreg serve``, started on first use when it is not running): they submit the
command's arguments as a job (:func:`run_job`), show the job's progress events, cancel it through
the service, and read the files it writes (:func:`read_pair_outputs`, :func:`read_plot_outputs`)
into plain records that a host turns into layers or entities. Only the standard library is used
here (and in :mod:`forestreg.client`), so this module imports in QGIS's and CloudCompare's Python
as they are.

Conventions are the CLI's: ``p_reference = matrix @ p_moving`` (pair, file coordinates), and
``p_centre = matrix @ p_scan`` (plot, ``poses.json``). A scan's scanner stands at its file's
origin unless a scanner position was given.
"""

from __future__ import annotations

import csv
import os
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

from ..app.saved import SavedFileError, SavedPoses, SavedResult, read_scanner_positions, saved_crs

Matrix = list  # 4x4 nested lists of floats
ProgressCallback = Callable[[float, str], None]
LogCallback = Callable[[str], None]

#: environment variable naming the ``forestreg`` command to run (a path, or a command line)
CLI_ENV = "FORESTREG_CLI"

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2


class AdapterError(RuntimeError):
    """The service could not run the command, it stopped with an error, or left a file missing."""

    def __init__(self, message: str, returncode: Optional[int] = None, stderr: str = "") -> None:
        super().__init__(message)
        self.returncode = returncode
        self.stderr = stderr


class BadInputError(AdapterError):
    """The CLI exited with status 2: bad input (unreadable file, wrong unit, unknown parameter)."""


class CancelledError(AdapterError):
    """The run was cancelled and the service stopped the job."""


# ----------------------------------------------------------------------------- jobs


@dataclass
class PairJob:
    """``forestreg register REFERENCE MOVING --out OUT_DIR [--dr M] ...``"""

    reference: Union[str, Path]
    moving: Union[str, Path]
    out_dir: Union[str, Path]
    vop_radius_m: Optional[float] = None
    params_file: Optional[Union[str, Path]] = None
    scanner_positions: Sequence[Sequence[float]] = ()  # reference first, then moving
    units: Optional[str] = None
    write_registered: bool = False
    crs: Optional[str] = None  # --crs: of the scans' coordinates where they declare none (EPSG:code or WKT)
    extra_args: Sequence[str] = ()


@dataclass
class PlotJob:
    """``forestreg plot SCAN ... --out OUT_DIR [--centre SCAN] [--dr M] ...``"""

    scans: Sequence[Union[str, Path]]
    out_dir: Union[str, Path]
    centre: Optional[Union[str, Path]] = None
    vop_radius_m: Optional[float] = None
    params_file: Optional[Union[str, Path]] = None
    merged: Optional[Union[str, Path]] = None
    crs: Optional[str] = None  # --crs: of the scans' coordinates where they declare none (EPSG:code or WKT)
    extra_args: Sequence[str] = ()


def _python_executable() -> str:
    """A Python interpreter for ``-m forestreg.cli``: ``sys.executable`` unless the host embeds
    Python in its own binary (QGIS, CloudCompare), then ``python3``/``python`` from PATH."""
    exe = sys.executable or ""
    if Path(exe).name.lower().startswith("python"):
        return exe
    return shutil.which("python3") or shutil.which("python") or exe


def cli_command(cli: Union[None, str, Sequence[str]] = None) -> list[str]:
    """The command that runs the ``forestreg`` CLI, as a list.

    In order: ``cli`` (a path to the ``forestreg`` script, or a list such as
    ``[python, "-m", "forestreg.cli"]``), the ``FORESTREG_CLI`` environment variable, a
    ``forestreg`` on PATH, else ``python -m forestreg.cli``.
    """
    if cli is not None and not isinstance(cli, (str, Path)):
        return [str(c) for c in cli]
    text = str(cli or "").strip() or os.environ.get(CLI_ENV, "").strip()
    if text:
        # a path (which may contain spaces), else a command line such as "python3 -m forestreg.cli"
        return [text] if Path(text).exists() else shlex.split(text, posix=os.name != "nt")
    found = shutil.which("forestreg")
    if found:
        return [found]
    return [_python_executable(), "-m", "forestreg.cli"]


def _num(value: float) -> str:
    return repr(float(value))


def build_pair_command(job: PairJob, cli: Union[None, str, Sequence[str]] = None) -> list[str]:
    """The full command line of a pair registration (what the service runs, for display)."""
    return cli_command(cli) + build_pair_args(job)


def build_pair_args(job: PairJob) -> list[str]:
    """The CLI arguments of a pair registration (a job of the service)."""
    cmd = ["register", str(job.reference), str(job.moving), "--out", str(job.out_dir)]
    if job.vop_radius_m is not None:
        cmd += ["--dr", _num(job.vop_radius_m)]
    if job.params_file:
        cmd += ["--params", str(job.params_file)]
    for pos in job.scanner_positions:
        cmd += ["--scanner-position", ",".join(_num(v) for v in pos)]
    if job.units:
        cmd += ["--units", job.units]
    if job.write_registered:
        cmd.append("--write-registered")
    if job.crs:
        cmd += ["--crs", str(job.crs)]
    return cmd + [str(a) for a in job.extra_args]


def build_plot_command(job: PlotJob, cli: Union[None, str, Sequence[str]] = None) -> list[str]:
    """The full command line of a plot registration (for display)."""
    return cli_command(cli) + build_plot_args(job)


def build_plot_args(job: PlotJob) -> list[str]:
    """The CLI arguments of a plot registration (a job of the service)."""
    if not job.scans:
        raise AdapterError("a plot needs at least one scan file")
    cmd = ["plot", *[str(s) for s in job.scans], "--out", str(job.out_dir)]
    if job.centre:
        cmd += ["--centre", str(job.centre)]
    if job.vop_radius_m is not None:
        cmd += ["--dr", _num(job.vop_radius_m)]
    if job.params_file:
        cmd += ["--params", str(job.params_file)]
    if job.merged:
        cmd += ["--merged", str(job.merged)]
    if job.crs:
        cmd += ["--crs", str(job.crs)]
    return cmd + [str(a) for a in job.extra_args]


@dataclass
class CoregisterJob:
    """``forestreg coregister GROUND UAV --out OUT_DIR [--min-cluster-size N] [--voxel M] ...``"""

    ground: Union[str, Path]
    uav: Union[str, Path]
    out_dir: Union[str, Path]
    min_cluster_size: Optional[int] = None
    voxel_m: Optional[float] = None
    distance_threshold_m: Optional[float] = None
    crs: Optional[str] = None
    units: Optional[str] = None
    params_file: Optional[Union[str, Path]] = None
    extra_args: Sequence[str] = ()


@dataclass
class FuseJob:
    """``forestreg fuse GROUND UAV --out CLOUD [--transform FILE] [--epsilon M] [--cube M] ...``"""

    ground: Union[str, Path]
    uav: Union[str, Path]
    out: Union[str, Path]  # the fused cloud (.laz/.las)
    transform: Optional[Union[str, Path]] = None
    epsilon_m: Optional[float] = None
    cube_m: Optional[float] = None
    crs: Optional[str] = None
    units: Optional[str] = None
    params_file: Optional[Union[str, Path]] = None
    extra_args: Sequence[str] = ()


@dataclass
class TreesJob:
    """``forestreg trees CLOUD --out OUT_DIR [--transform FILE] [--field CSV] [--no-cylinders] ...``"""

    cloud: Union[str, Path]
    out_dir: Union[str, Path]
    transform: Optional[Union[str, Path]] = None
    field: Optional[Union[str, Path]] = None
    cylinders: bool = True
    single_tree: Optional[str] = None  # None (decided from the cloud), "auto", "yes" or "no"
    report: bool = True
    crs: Optional[str] = None
    units: Optional[str] = None
    params_file: Optional[Union[str, Path]] = None
    extra_args: Sequence[str] = ()


@dataclass
class EvaluateJob:
    """``forestreg evaluate TREES FIELD --out OUT_DIR [--name N] [--also [NAME=]TREES] [--by position|id] ...``"""

    trees: Union[str, Path]
    field: Union[str, Path]
    out_dir: Union[str, Path]
    name: Optional[str] = None
    also: Sequence[str] = ()
    by: str = "position"
    max_distance_m: float = 1.0
    extra_args: Sequence[str] = ()


@dataclass
class ChangeJob:
    """``forestreg change BEFORE AFTER --out OUT_DIR [--no-report] [--units U] [--units-before U] ...``"""

    before: Union[str, Path]
    after: Union[str, Path]
    out_dir: Union[str, Path]
    report: bool = True
    crs: Optional[str] = None
    units: Optional[str] = None
    units_before: Optional[str] = None
    units_after: Optional[str] = None
    params_file: Optional[Union[str, Path]] = None
    extra_args: Sequence[str] = ()


def _options(pairs: Sequence[tuple[str, object]]) -> list[str]:
    """``--option value`` for each pair whose value is given (numbers as the CLI reads them)."""
    cmd: list[str] = []
    for option, value in pairs:
        if value is None or value == "":
            continue
        cmd += [option, _num(value) if isinstance(value, float) else str(value)]
    return cmd


def build_coregister_args(job: CoregisterJob) -> list[str]:
    """The CLI arguments of a co-registration (a job of the service)."""
    cmd = ["coregister", str(job.ground), str(job.uav), "--out", str(job.out_dir)]
    cmd += _options(
        [
            ("--min-cluster-size", None if job.min_cluster_size is None else int(job.min_cluster_size)),
            ("--voxel", None if job.voxel_m is None else float(job.voxel_m)),
            ("--distance-threshold", None if job.distance_threshold_m is None else float(job.distance_threshold_m)),
            ("--crs", job.crs),
            ("--units", job.units),
            ("--params", job.params_file),
        ]
    )
    return cmd + [str(a) for a in job.extra_args]


def build_fuse_args(job: FuseJob) -> list[str]:
    """The CLI arguments of a fusion (a job of the service)."""
    cmd = ["fuse", str(job.ground), str(job.uav), "--out", str(job.out)]
    cmd += _options(
        [
            ("--transform", job.transform),
            ("--epsilon", None if job.epsilon_m is None else float(job.epsilon_m)),
            ("--cube", None if job.cube_m is None else float(job.cube_m)),
            ("--crs", job.crs),
            ("--units", job.units),
            ("--params", job.params_file),
        ]
    )
    return cmd + [str(a) for a in job.extra_args]


SINGLE_TREE_CHOICES = ("auto", "yes", "no")


def build_trees_args(job: TreesJob) -> list[str]:
    """The CLI arguments of a trees run (a job of the service)."""
    cmd = ["trees", str(job.cloud), "--out", str(job.out_dir)]
    cmd += _options([("--transform", job.transform), ("--field", job.field)])
    if not job.cylinders:
        cmd.append("--no-cylinders")
    if job.single_tree:
        if job.single_tree not in SINGLE_TREE_CHOICES:
            raise AdapterError(f"single tree: {job.single_tree!r} is none of {', '.join(SINGLE_TREE_CHOICES)}")
        cmd += ["--single-tree", job.single_tree]
    if not job.report:
        cmd.append("--no-report")
    cmd += _options([("--crs", job.crs), ("--units", job.units), ("--params", job.params_file)])
    return cmd + [str(a) for a in job.extra_args]


EVALUATE_BY = ("position", "id")


def build_evaluate_args(job: EvaluateJob) -> list[str]:
    """The CLI arguments of an evaluation against field records (a job of the service)."""
    if job.by not in EVALUATE_BY:
        raise AdapterError(f"match by: {job.by!r} is none of {', '.join(EVALUATE_BY)}")
    cmd = ["evaluate", str(job.trees), str(job.field), "--out", str(job.out_dir)]
    cmd += _options([("--name", job.name)])
    for other in job.also:
        cmd += ["--also", str(other)]
    cmd += ["--by", job.by, "--max-distance", _num(job.max_distance_m)]
    return cmd + [str(a) for a in job.extra_args]


def build_change_args(job: ChangeJob) -> list[str]:
    """The CLI arguments of a re-survey comparison (a job of the service)."""
    cmd = ["change", str(job.before), str(job.after), "--out", str(job.out_dir)]
    if not job.report:
        cmd.append("--no-report")
    cmd += _options(
        [
            ("--crs", job.crs),
            ("--units", job.units),
            ("--units-before", job.units_before),
            ("--units-after", job.units_after),
            ("--params", job.params_file),
        ]
    )
    return cmd + [str(a) for a in job.extra_args]


#: the command of each job type and the function that builds its arguments
JOB_ARGS = {
    PairJob: build_pair_args,
    PlotJob: build_plot_args,
    CoregisterJob: build_coregister_args,
    FuseJob: build_fuse_args,
    TreesJob: build_trees_args,
    EvaluateJob: build_evaluate_args,
    ChangeJob: build_change_args,
}


def build_args(job) -> list[str]:
    """The CLI arguments of any job of :data:`JOB_ARGS`."""
    try:
        return JOB_ARGS[type(job)](job)
    except KeyError:
        raise AdapterError(f"not a forestreg job: {type(job).__name__}") from None


# ----------------------------------------------------------------------------- running (through the service)


@dataclass
class JobRun:
    """One finished job of the service."""

    job_id: str
    args: list[str]
    returncode: int
    message: str  # the command's last line ("ok: ..." / "failed: ..." / its error)
    result: object = None  # the command's result.json (or summary) as the service read it
    seconds: float = 0.0


def _subprocess_env(command: Sequence[str]) -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    env.setdefault("MPLBACKEND", "Agg")  # the CLI draws figures: never open a window
    # ``python -m forestreg.cli`` from a plugin folder named ``forestreg`` that is not installed:
    # let that interpreter find this copy (an installed ``forestreg`` script keeps its own)
    package = Path(__file__).resolve().parents[1]
    if package.name == "forestreg" and "forestreg.cli" in command:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(package.parent), env.get("PYTHONPATH", "")) if p)
    return env


#: What the engine imports (``forestreg serve`` and its jobs): a Python needs these before it can
#: run ``python -m forestreg.cli``. (The hosts themselves need only the standard library.)
ENGINE_MODULES = ("numpy", "scipy", "open3d", "laspy", "numba", "hdbscan", "fastapi", "uvicorn")


def _version() -> str:
    try:
        from .._version import __version__

        return __version__
    except ImportError:  # pragma: no cover - the adapter outside its package
        return "VERSION"


def engine_problem(cli: Union[None, str, Sequence[str]] = None) -> Optional[str]:
    """``None`` when the command that starts the service can run forestreg's engine, else one
    message naming what is missing and the two ways to install it.

    A ``forestreg`` command (on PATH, ``FORESTREG_CLI`` or the host's setting) is a Python
    environment of its own, trusted here (if it is broken the service's start says why). When
    the command is ``python -m forestreg.cli`` (no ``forestreg`` command found), that Python
    must have the engine's modules (:data:`ENGINE_MODULES`); they are looked up without being
    imported."""
    command = cli_command(cli)
    if "forestreg.cli" not in command:
        return None
    python = command[0]
    code = f"import importlib.util as u; print(' '.join(m for m in {ENGINE_MODULES!r} if u.find_spec(m) is None))"
    try:
        run = subprocess.run(
            [python, "-c", code], capture_output=True, text=True, timeout=60, env=_subprocess_env(command)
        )
        missing = (
            run.stdout.split()
            if run.returncode == 0
            else ["(the interpreter failed: " + (run.stderr.strip().splitlines() or ["?"])[-1] + ")"]
        )
    except (OSError, subprocess.SubprocessError) as exc:
        missing = [f"(the interpreter cannot be run: {exc})"]
    if not missing:
        return None
    wheel = f"forestreg-{_version()}-py3-none-any.whl"
    return (
        f"forestreg cannot run its engine: no 'forestreg' command was found, and the Python at {python} "
        f"lacks {', '.join(missing)}. Install forestreg in one of two ways: "
        f"(1) in its own environment, 'python3 -m venv ~/forestreg-env' then "
        f"'~/forestreg-env/bin/pip install {wheel}', and set the environment variable {CLI_ENV} "
        f"(or the algorithm's 'forestreg command') to ~/forestreg-env/bin/forestreg; or "
        f"(2) into this Python: '{python} -m pip install --user {wheel}'. "
        f"Then restart QGIS (or CloudCompare). See the documentation's QGIS page."
    )


def service_client(cli: Union[None, str, Sequence[str]] = None, state_dir: Optional[Union[str, Path]] = None):
    """A client of the forestreg job service, started with ``cli serve`` when none runs (its
    state folder: ``state_dir``, else ``$FORESTREG_SERVICE_DIR`` or the user's data directory).
    When none runs and the command cannot run the engine (:func:`engine_problem`), an
    :class:`AdapterError` says what is missing and how to install it."""
    from ..client import ServiceError, connect

    command = cli_command(cli)
    try:
        return connect(state_dir, start=False)
    except ServiceError:
        pass
    problem = engine_problem(command)
    if problem:
        raise AdapterError(problem)
    try:
        return connect(state_dir, command=command, env=_subprocess_env(command))
    except ServiceError as exc:
        raise AdapterError(f"the forestreg service is not available: {exc}") from exc


def run_job(
    args: Sequence[str],
    progress: Optional[ProgressCallback] = None,
    log: Optional[LogCallback] = None,
    cancelled: Optional[Callable[[], bool]] = None,
    cli: Union[None, str, Sequence[str]] = None,
    cwd: Optional[Union[str, Path]] = None,
    timeout_s: Optional[float] = None,
    state_dir: Optional[Union[str, Path]] = None,
) -> JobRun:
    """Run a ``forestreg`` command (its arguments, without the program) as a job of the service.

    ``progress(fraction, message)`` is called for each progress event of the job, ``log(line)``
    for each output line; ``cancelled()`` is asked about once a second and a true answer cancels
    the job (:class:`CancelledError`). Arguments the CLI refuses and exit status 2 raise
    :class:`BadInputError` with the CLI's message; exit status 0 and 1 (a registration that failed,
    with its reason in ``result.json``) return the :class:`JobRun`; anything else raises
    :class:`AdapterError`.
    """
    from ..client import ServiceError

    args = [str(a) for a in args]
    client = service_client(cli, state_dir)
    t0 = time.monotonic()
    try:
        job_id = client.submit(args, cwd)
    except ServiceError as exc:
        if exc.status == 400:
            raise BadInputError(f"forestreg: bad input: {exc.detail}", EXIT_BAD_INPUT, exc.detail) from None
        raise AdapterError(str(exc)) from None
    try:
        final = client.wait(job_id, progress=progress, log=log, cancelled=cancelled, timeout=timeout_s)
    except TimeoutError:
        client.cancel(job_id)
        raise AdapterError(f"the forestreg job took longer than {timeout_s:.0f} s and was cancelled") from None
    except ServiceError as exc:
        raise AdapterError(str(exc)) from None
    code, message = final.get("exit_code"), final.get("message") or ""
    if final["status"] == "cancelled":
        raise CancelledError("cancelled: the forestreg job was stopped", code)
    if code == EXIT_BAD_INPUT:
        raise BadInputError(f"forestreg: bad input: {message}", code, message)
    if final["status"] != "done" or code not in (EXIT_OK, EXIT_FAILED):
        raise AdapterError(
            f"forestreg job {final['status']} (exit status {code}): {message or 'no message'}", code, message
        )
    return JobRun(job_id, args, code, message, final.get("result"), time.monotonic() - t0)


# ----------------------------------------------------------------------------- reading outputs


def _need(path: Path) -> Path:
    if not path.is_file():
        raise AdapterError(f"forestreg output {path.name} is missing in {path.parent}")
    return path


def read_json(path: Union[str, Path]) -> dict:
    """The JSON object of an output file (:class:`AdapterError` when missing or not valid JSON)."""
    from ..app.saved import read_json_object

    try:
        return read_json_object(_need(Path(path)))
    except SavedFileError as exc:
        raise AdapterError(str(exc)) from exc


def apply_matrix(matrix: Matrix, point: Sequence[float]) -> tuple[float, float, float]:
    """``matrix @ [x, y, z, 1]`` for one point (plain lists)."""
    x, y, z = (float(v) for v in point[:3])
    return tuple(float(r[0] * x + r[1] * y + r[2] * z + r[3]) for r in matrix[:3])  # type: ignore[return-value]


def read_transform_txt(path: Union[str, Path]) -> Matrix:
    """The 4x4 matrix of a ``transform.txt`` (four lines of four numbers)."""
    rows = [[float(v) for v in line.split()] for line in _need(Path(path)).read_text().splitlines() if line.strip()]
    if len(rows) != 4 or any(len(r) != 4 for r in rows):
        raise AdapterError(f"{path}: expected four lines of four numbers")
    return rows


def read_vops_csv(path: Union[str, Path], scan: str, to_frame: Optional[Matrix] = None) -> list[dict]:
    """The rows of a ``*_vops.csv`` as records: ``scan, id, x, y, z`` (in the frame ``to_frame``
    maps into; the file's coordinates without it), ``x_file, y_file, z_file``, ``radius_m``,
    ``support_points``, ``matched`` (bool) and ``matched_with`` (the other scan's VOP id or None)."""
    rows = []
    with _need(Path(path)).open(newline="", encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            p = (float(row["x"]), float(row["y"]), float(row["z"]))
            q = apply_matrix(to_frame, p) if to_frame is not None else p
            other = (row.get("matched_with") or "").strip()
            rows.append(
                {
                    "scan": scan,
                    "id": int(row["id"]),
                    "x": q[0],
                    "y": q[1],
                    "z": q[2],
                    "x_file": p[0],
                    "y_file": p[1],
                    "z_file": p[2],
                    "radius_m": float(row["radius_m"]),
                    "support_points": int(row["support_points"]),
                    "matched": bool(other),
                    "matched_with": int(other) if other else None,
                }
            )
    return rows


@dataclass
class HostOutputs:
    """What a host shows after a run: the summary, scanner positions and VOPs as plain records."""

    kind: str  # "pair" or "plot"
    out_dir: Path
    status: str  # "ok" / "failed" for a pair; "ok" when every scan registered, else "failed"
    frame: str  # the scan whose coordinates the records are in (reference / centre scan)
    summary: dict  # result.json (pair) or poses.json (plot), as written, for a host to show
    scanners: list[dict] = field(default_factory=list)  # name, role, status, x, y, z, reason
    vops: list[dict] = field(default_factory=list)
    reason: str = ""
    #: the pair's ``result.json``, typed (None for a plot)
    result: Optional[SavedResult] = None

    @property
    def matrix(self) -> Optional[Matrix]:
        """The pair's ``p_reference = matrix @ p_moving`` (None for a failed pair or a plot)."""
        return self.result.matrix if self.result is not None else None

    @property
    def matched(self) -> int:
        """The pair's matched trunk shadows (VOPs); 0 for a plot or when none were matched."""
        return (self.result.matched or 0) if self.result is not None else 0


def _scanner(
    name: str, role: str, status: str, position: Sequence[float], registered: bool, reason: str, **more: str
) -> dict:
    """A scanner record (:data:`SCANNER_FIELDS`)."""
    x, y, z = position
    return {
        "name": name,
        "role": role,
        "status": status,
        "registered": registered,
        "x": x,
        "y": y,
        "z": z,
        "reason": reason,
        **more,
    }


def read_pair_outputs(out_dir: Union[str, Path], scanner_positions: Sequence[Sequence[float]] = ()) -> HostOutputs:
    """``result.json`` and the two VOP files of ``forestreg register`` as records in the
    reference scan's coordinates: the moving scan's VOPs and scanner are mapped by the matrix
    when the registration is ok (left in the moving file's coordinates, flagged, when it failed)."""
    out = Path(out_dir)
    summary = read_json(out / "result.json")
    result = SavedResult.from_dict(summary)
    matrix = result.matrix
    ref_name = result.reference or "reference"
    mov_name = result.moving or "moving"
    ref_pos = tuple(scanner_positions[0]) if len(scanner_positions) > 0 else (0.0, 0.0, 0.0)
    mov_pos = tuple(scanner_positions[1]) if len(scanner_positions) > 1 else (0.0, 0.0, 0.0)
    scanners = [
        _scanner(ref_name, "reference", "ok", ref_pos, True, ""),
        _scanner(
            mov_name,
            "moving",
            result.status,
            apply_matrix(matrix, mov_pos) if matrix is not None else mov_pos,
            matrix is not None,
            result.reason,
        ),
    ]
    vops: list[dict] = []
    # a registration that fails before VOPs exist writes no VOP files: that is not an error
    if (out / "reference_vops.csv").is_file() or result.ok:
        vops += [dict(v, registered=True) for v in read_vops_csv(out / "reference_vops.csv", ref_name)]
        vops += [
            dict(v, registered=matrix is not None)
            for v in read_vops_csv(out / "moving_vops.csv", mov_name, to_frame=matrix)
        ]
    return HostOutputs("pair", out, result.status, ref_name, summary, scanners, vops, result.reason, result)


def read_plot_outputs(out_dir: Union[str, Path]) -> HostOutputs:
    """``poses.json`` of ``forestreg plot`` as scanner records in the centre scan's coordinates
    (scanner positions from ``project.json`` where given, else each file's origin)."""
    out = Path(out_dir)
    summary = read_json(out / "poses.json")
    poses = SavedPoses.from_dict(summary)
    project_file = out / "project.json"
    try:
        positions = read_scanner_positions(project_file) if project_file.is_file() else {}
    except SavedFileError as exc:
        raise AdapterError(str(exc)) from exc
    scanners = []
    for s in poses.scans:
        p = positions.get(s.name, (0.0, 0.0, 0.0))
        scanners.append(
            _scanner(
                s.name,
                "centre" if s.name == poses.frame else "scan",
                s.status,
                apply_matrix(s.matrix, p) if s.registered else p,
                s.registered,
                s.reason,
                reference=s.reference,
            )
        )
    return HostOutputs(
        "plot", out, "ok" if not poses.not_registered else "failed", poses.frame, summary, scanners, [], poses.reason()
    )


# ----------------------------------------------------------------------------- layer files

SCANNER_FIELDS = ["name", "role", "status", "registered", "x", "y", "z", "reason"]
VOP_FIELDS = [
    "scan",
    "id",
    "x",
    "y",
    "z",
    "x_file",
    "y_file",
    "z_file",
    "radius_m",
    "support_points",
    "matched",
    "matched_with",
    "registered",
]


def write_layer_csv(path: Union[str, Path], records: Sequence[dict], fields: Sequence[str]) -> Path:
    """Records as a CSV a GIS opens as a point layer (``x``, ``y``, ``z`` columns; booleans 0/1)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(fields)
        for r in records:
            w.writerow(
                ["" if r.get(k) is None else int(r[k]) if isinstance(r.get(k), bool) else r.get(k) for k in fields]
            )
    os.replace(tmp, path)
    return path


@dataclass(frozen=True)
class LayerFiles:
    """The layer CSVs written for a host: the scanners, and the VOPs of a pair (None for a plot)."""

    scanners: Path
    vops: Optional[Path] = None


def write_layer_files(outputs: HostOutputs) -> LayerFiles:
    """``layer_scanners.csv`` (and ``layer_vops.csv`` for a pair) in the output folder."""
    scanners = write_layer_csv(outputs.out_dir / "layer_scanners.csv", outputs.scanners, SCANNER_FIELDS)
    vops = (
        write_layer_csv(outputs.out_dir / "layer_vops.csv", outputs.vops, VOP_FIELDS)
        if outputs.kind == "pair"
        else None
    )
    return LayerFiles(scanners, vops)


def output_crs(summary: object) -> Optional[str]:
    """The CRS a run's outputs are in, as its ``result.json`` or ``poses.json`` names it
    (:func:`~forestreg.app.saved.saved_crs`): the EPSG id, else the WKT; None for local coordinates."""
    return saved_crs(summary)


def delimited_text_uri(path: Union[str, Path], crs: Optional[str] = None) -> str:
    """A QGIS ``delimitedtext`` provider URI for a layer CSV (points from x, y, z)."""
    uri = (
        Path(path).resolve().as_uri()
        + "?type=csv&delimiter=,&xField=x&yField=y&zField=z&detectTypes=yes&geomType=point&spatialIndex=no&subsetIndex=no&watchFile=no"
    )
    if crs:
        uri += f"&crs={crs}"
    return uri


# ----------------------------------------------------------------------------- one call


def register(
    job: Union[PairJob, PlotJob],
    cli: Union[None, str, Sequence[str]] = None,
    progress: Optional[ProgressCallback] = None,
    log: Optional[LogCallback] = None,
    cancelled: Optional[Callable[[], bool]] = None,
) -> HostOutputs:
    """Run ``forestreg register`` (a :class:`PairJob`) or ``forestreg plot`` (a :class:`PlotJob`)
    for ``job`` as a job of the service and read what it wrote (also the layer CSVs)."""
    pair = isinstance(job, PairJob)
    run_job(
        build_pair_args(job) if pair else build_plot_args(job), progress=progress, log=log, cancelled=cancelled, cli=cli
    )
    outputs = read_pair_outputs(job.out_dir, job.scanner_positions) if pair else read_plot_outputs(job.out_dir)
    if pair and outputs.status == "ok":
        _need(Path(job.out_dir) / "transform.txt")
    write_layer_files(outputs)
    return outputs


#: :func:`register` under the names of its two jobs (the job's type decides what runs)
register_pair = register_plot = register


# ----------------------------------------------------------------------------- layers.gpkg and clouds

#: the GIS layers an output folder of ``trees``, ``change``, ``plot`` and ``coregister`` holds
LAYERS_FILE = "layers.gpkg"
#: point cloud files QGIS (>= 3.18) opens with its "pdal" provider
POINT_CLOUD_SUFFIXES = (".las", ".laz", ".copc.laz")


@dataclass(frozen=True)
class GpkgLayer:
    """One feature layer of a ``layers.gpkg``: its name, its QML style (``layer_styles``; "" when
    none) and the URI QGIS's "ogr" provider opens it with."""

    name: str
    style: str
    uri: str


def gpkg_layers(path: Union[str, Path]) -> list[GpkgLayer]:
    """The feature layers of a GeoPackage in the order of ``gpkg_contents`` with their default
    QML styles; [] when the file does not exist (a run that wrote no layers). Standard library only."""
    import sqlite3

    path = Path(path)
    if not path.is_file():
        return []
    try:
        con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise AdapterError(f"{path}: not a GeoPackage ({exc})") from exc
    try:
        names = [
            r[0]
            for r in con.execute("SELECT table_name FROM gpkg_contents WHERE data_type = 'features' ORDER BY rowid")
        ]
        styles: dict[str, str] = {}
        try:
            for table, qml in con.execute(
                "SELECT f_table_name, styleQML FROM layer_styles WHERE useAsDefault ORDER BY id"
            ):
                styles.setdefault(table, qml or "")
        except sqlite3.OperationalError:  # no layer_styles table
            pass
    except sqlite3.Error as exc:
        raise AdapterError(f"{path}: not a GeoPackage ({exc})") from exc
    finally:
        con.close()
    return [GpkgLayer(n, styles.get(n, ""), f"{path.resolve()}|layername={n}") for n in names]


def is_point_cloud_file(path: Union[None, str, Path]) -> bool:
    """Whether ``path`` is a LAS/LAZ/COPC file that exists (what a point cloud layer opens)."""
    return bool(path) and Path(path).is_file() and Path(path).name.lower().endswith(POINT_CLOUD_SUFFIXES)
