"""What the plugin hosts (QGIS, CloudCompare) share, without any host or Qt import.

The hosts never run the engine in their own process: they build a ``forestreg`` command line,
run it as a subprocess (:func:`run_cli`, progress parsed from the CLI's progress bar on stderr),
and read the files it writes (:func:`read_pair_outputs`, :func:`read_plot_outputs`) into plain
records that a host turns into layers or entities. Only the standard library is used here, so
this module imports in QGIS's and CloudCompare's Python as they are.

Conventions are the CLI's: ``p_reference = matrix @ p_moving`` (pair, file coordinates), and
``p_centre = matrix @ p_scan`` (plot, ``poses.json``). A scan's scanner stands at its file's
origin unless a scanner position was given.
"""

from __future__ import annotations

import csv
import json
import os
import queue
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

Matrix = list  # 4x4 nested lists of floats
ProgressCallback = Callable[[float, str], None]
LogCallback = Callable[[str], None]

#: environment variable naming the ``forestreg`` command to run (a path, or a command line)
CLI_ENV = "FORESTREG_CLI"

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2


class AdapterError(RuntimeError):
    """The CLI could not be run, stopped with an error, or left an expected file missing."""

    def __init__(self, message: str, returncode: Optional[int] = None, stderr: str = "") -> None:
        super().__init__(message)
        self.returncode = returncode
        self.stderr = stderr


class BadInputError(AdapterError):
    """The CLI exited with status 2: bad input (unreadable file, wrong unit, unknown parameter)."""


class CancelledError(AdapterError):
    """The run was cancelled and the CLI process was stopped."""


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
    """The full command line of a pair registration (progress bar on, so no ``--quiet``)."""
    cmd = cli_command(cli) + ["register", str(job.reference), str(job.moving), "--out", str(job.out_dir)]
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
    return cmd + [str(a) for a in job.extra_args]


def build_plot_command(job: PlotJob, cli: Union[None, str, Sequence[str]] = None) -> list[str]:
    """The full command line of a plot registration."""
    if not job.scans:
        raise AdapterError("a plot needs at least one scan file")
    cmd = cli_command(cli) + ["plot", *[str(s) for s in job.scans], "--out", str(job.out_dir)]
    if job.centre:
        cmd += ["--centre", str(job.centre)]
    if job.vop_radius_m is not None:
        cmd += ["--dr", _num(job.vop_radius_m)]
    if job.params_file:
        cmd += ["--params", str(job.params_file)]
    if job.merged:
        cmd += ["--merged", str(job.merged)]
    return cmd + [str(a) for a in job.extra_args]


# ----------------------------------------------------------------------------- running

# a tqdm line of the CLI: "register: slicing          30%|█████      | 00:05"
_PROGRESS = re.compile(r"^(?P<desc>[\w.-]+)(?::\s*(?P<msg>.*?))?\s+(?P<pct>\d{1,3})%\|")
_ERROR = re.compile(r"^forestreg: error:\s*(?P<msg>.*)$")


def parse_progress(line: str) -> Optional[tuple[float, str]]:
    """``(fraction, message)`` of one progress-bar line of the CLI, or None for other lines."""
    m = _PROGRESS.match(line.strip())
    if m is None:
        return None
    return min(max(int(m.group("pct")) / 100.0, 0.0), 1.0), (m.group("msg") or m.group("desc")).strip()


@dataclass
class CliRun:
    """One finished CLI run."""

    command: list[str]
    returncode: int
    stdout: str
    stderr_lines: list[str] = field(default_factory=list)  # without the progress-bar lines
    seconds: float = 0.0

    @property
    def error_message(self) -> str:
        """The CLI's one-line error ("forestreg: error: ..."), else the last stderr line."""
        for line in reversed(self.stderr_lines):
            m = _ERROR.match(line)
            if m:
                return m.group("msg")
        return self.stderr_lines[-1] if self.stderr_lines else ""


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


def run_cli(
    command: Sequence[str],
    progress: Optional[ProgressCallback] = None,
    log: Optional[LogCallback] = None,
    cancelled: Optional[Callable[[], bool]] = None,
    cwd: Optional[Union[str, Path]] = None,
    timeout_s: Optional[float] = None,
) -> CliRun:
    """Run a ``forestreg`` command line in a separate process.

    ``progress(fraction, message)`` is called for each progress-bar update on stderr, ``log(line)``
    for every other stderr and stdout line; ``cancelled()`` is polled and a true answer stops the
    process (:class:`CancelledError`). Exit status 2 raises :class:`BadInputError` with the CLI's
    message; status 0 and 1 (a registration that failed, with its reason in ``result.json``) return
    the :class:`CliRun`; any other status raises :class:`AdapterError`.
    """
    command = [str(c) for c in command]
    kwargs = {}
    if os.name == "nt":  # no console window from inside a GUI host
        kwargs["creationflags"] = getattr(subprocess, "CREATE_NO_WINDOW", 0)
    t0 = time.monotonic()
    try:
        proc = subprocess.Popen(
            command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            cwd=None if cwd is None else str(cwd), env=_subprocess_env(command), **kwargs,
        )
    except OSError as exc:
        raise AdapterError(f"cannot start the forestreg command {command[0]!r}: {exc}") from exc

    stderr_lines: list[str] = []
    stdout_parts: list[str] = []
    events: "queue.Queue[tuple]" = queue.Queue()  # callbacks run in the caller's thread, not the readers'

    def handle_line(line: str) -> None:
        line = line.rstrip()
        if not line:
            return
        parsed = parse_progress(line)
        if parsed is not None:
            events.put(("progress", parsed))
        else:
            stderr_lines.append(line)
            events.put(("log", line))

    def read_stderr() -> None:
        buf = b""
        while True:
            chunk = proc.stderr.read1(4096) if hasattr(proc.stderr, "read1") else proc.stderr.read(1)
            if not chunk:
                break
            buf += chunk
            parts = re.split(rb"[\r\n]", buf)
            buf = parts.pop()
            for raw in parts:
                handle_line(raw.decode("utf-8", "replace"))
        if buf:
            handle_line(buf.decode("utf-8", "replace"))

    def read_stdout() -> None:
        for raw in iter(proc.stdout.readline, b""):
            text = raw.decode("utf-8", "replace")
            stdout_parts.append(text)
            if text.strip():
                events.put(("log", text.rstrip()))

    def deliver() -> None:
        while True:
            try:
                kind, payload = events.get_nowait()
            except queue.Empty:
                return
            if kind == "progress" and progress is not None:
                progress(*payload)
            elif kind == "log" and log is not None:
                log(payload)

    threads = [threading.Thread(target=read_stderr, daemon=True), threading.Thread(target=read_stdout, daemon=True)]
    for t in threads:
        t.start()
    try:
        while True:
            try:
                proc.wait(timeout=0.1)
                break
            except subprocess.TimeoutExpired:
                pass
            deliver()
            if cancelled is not None and cancelled():
                _stop(proc)
                raise CancelledError("cancelled: the forestreg process was stopped", proc.returncode)
            if timeout_s is not None and time.monotonic() - t0 > timeout_s:
                _stop(proc)
                raise AdapterError(f"the forestreg process took longer than {timeout_s:.0f} s and was stopped", proc.returncode)
    finally:
        for t in threads:
            t.join(timeout=5)
        for stream in (proc.stdout, proc.stderr):
            try:
                stream.close()
            except Exception:  # pragma: no cover
                pass
    deliver()
    run = CliRun(command, proc.returncode, "".join(stdout_parts), stderr_lines, time.monotonic() - t0)
    if run.returncode == EXIT_BAD_INPUT:
        raise BadInputError(f"forestreg: bad input: {run.error_message}", run.returncode, "\n".join(stderr_lines))
    if run.returncode not in (EXIT_OK, EXIT_FAILED):
        raise AdapterError(
            f"forestreg stopped with exit status {run.returncode}: {run.error_message or 'no message'}",
            run.returncode, "\n".join(stderr_lines),
        )
    return run


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:  # pragma: no cover
        proc.kill()
        proc.wait()


# ----------------------------------------------------------------------------- reading outputs


def _need(path: Path) -> Path:
    if not path.is_file():
        raise AdapterError(f"forestreg output {path.name} is missing in {path.parent}")
    return path


def read_json(path: Union[str, Path]) -> dict:
    path = _need(Path(path))
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise AdapterError(f"{path}: not valid JSON ({exc})") from exc


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
            rows.append({
                "scan": scan, "id": int(row["id"]), "x": q[0], "y": q[1], "z": q[2],
                "x_file": p[0], "y_file": p[1], "z_file": p[2],
                "radius_m": float(row["radius_m"]), "support_points": int(row["support_points"]),
                "matched": bool(other), "matched_with": int(other) if other else None,
            })
    return rows


@dataclass
class HostOutputs:
    """What a host shows after a run: the summary, scanner positions and VOPs as plain records."""

    kind: str  # "pair" or "plot"
    out_dir: Path
    status: str  # "ok" / "failed" for a pair; "ok" when every scan registered, else "failed"
    frame: str  # the scan whose coordinates the records are in (reference / centre scan)
    summary: dict  # result.json (pair) or poses.json (plot)
    scanners: list[dict] = field(default_factory=list)  # name, role, status, x, y, z, reason
    vops: list[dict] = field(default_factory=list)
    reason: str = ""

    @property
    def matrix(self) -> Optional[Matrix]:
        """The pair's ``p_reference = matrix @ p_moving`` (None for a failed pair or a plot)."""
        return self.summary.get("matrix") if self.kind == "pair" else None


def read_pair_outputs(out_dir: Union[str, Path], scanner_positions: Sequence[Sequence[float]] = ()) -> HostOutputs:
    """``result.json`` and the two VOP files of ``forestreg register`` as records in the
    reference scan's coordinates: the moving scan's VOPs and scanner are mapped by the matrix
    when the registration is ok (left in the moving file's coordinates, flagged, when it failed)."""
    out = Path(out_dir)
    result = read_json(out / "result.json")
    status = result.get("status", "failed")
    matrix = result.get("matrix") if status == "ok" else None
    ref_name = result.get("reference") or "reference"
    mov_name = result.get("moving") or "moving"
    ref_pos = tuple(scanner_positions[0]) if len(scanner_positions) > 0 else (0.0, 0.0, 0.0)
    mov_pos = tuple(scanner_positions[1]) if len(scanner_positions) > 1 else (0.0, 0.0, 0.0)
    scanners = [{"name": ref_name, "role": "reference", "status": "ok", "registered": True, "x": ref_pos[0], "y": ref_pos[1], "z": ref_pos[2], "reason": ""}]
    m = apply_matrix(matrix, mov_pos) if matrix is not None else mov_pos
    scanners.append({"name": mov_name, "role": "moving", "status": status, "registered": matrix is not None, "x": m[0], "y": m[1], "z": m[2], "reason": result.get("reason") or ""})
    vops: list[dict] = []
    # a registration that fails before VOPs exist writes no VOP files: that is not an error
    if (out / "reference_vops.csv").is_file() or status == "ok":
        vops += read_vops_csv(out / "reference_vops.csv", ref_name)
        vops += read_vops_csv(out / "moving_vops.csv", mov_name, to_frame=matrix)
    for row in vops:
        row["registered"] = row["scan"] == ref_name or matrix is not None
    return HostOutputs("pair", out, status, ref_name, result, scanners, vops, result.get("reason") or "")


def read_plot_outputs(out_dir: Union[str, Path]) -> HostOutputs:
    """``poses.json`` of ``forestreg plot`` as scanner records in the centre scan's coordinates
    (scanner positions from ``project.json`` where given, else each file's origin)."""
    out = Path(out_dir)
    poses = read_json(out / "poses.json")
    positions: dict[str, tuple] = {}
    project_file = out / "project.json"
    if project_file.is_file():
        for s in read_json(project_file).get("scans", []):
            if s.get("scanner_position"):
                positions[s["name"]] = tuple(float(v) for v in s["scanner_position"][:3])
    frame = poses.get("frame") or ""
    scanners = []
    for name, entry in (poses.get("scans") or {}).items():
        matrix = entry.get("matrix")
        p = positions.get(name, (0.0, 0.0, 0.0))
        q = apply_matrix(matrix, p) if matrix is not None else p
        scanners.append({
            "name": name, "role": "centre" if name == frame else "scan", "status": entry.get("status", "failed"),
            "registered": matrix is not None, "x": q[0], "y": q[1], "z": q[2],
            "reason": entry.get("reason") or "", "reference": entry.get("reference") or "",
        })
    failed = [s["name"] for s in scanners if not s["registered"]]
    reason = "; ".join(f"{s['name']}: {s['reason'] or 'not registered'}" for s in scanners if not s["registered"])
    return HostOutputs("plot", out, "ok" if not failed else "failed", frame, poses, scanners, [], reason)


# ----------------------------------------------------------------------------- layer files

SCANNER_FIELDS = ["name", "role", "status", "registered", "x", "y", "z", "reason"]
VOP_FIELDS = ["scan", "id", "x", "y", "z", "x_file", "y_file", "z_file", "radius_m", "support_points", "matched", "matched_with", "registered"]


def write_layer_csv(path: Union[str, Path], records: Sequence[dict], fields: Sequence[str]) -> Path:
    """Records as a CSV a GIS opens as a point layer (``x``, ``y``, ``z`` columns; booleans 0/1)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(fields)
        for r in records:
            w.writerow(["" if r.get(k) is None else int(r[k]) if isinstance(r.get(k), bool) else r.get(k) for k in fields])
    os.replace(tmp, path)
    return path


def write_layer_files(outputs: HostOutputs) -> dict[str, Path]:
    """``layer_scanners.csv`` (and ``layer_vops.csv`` for a pair) in the output folder; returns
    ``{"scanners": path, "vops": path}``."""
    files = {"scanners": write_layer_csv(outputs.out_dir / "layer_scanners.csv", outputs.scanners, SCANNER_FIELDS)}
    if outputs.kind == "pair":
        files["vops"] = write_layer_csv(outputs.out_dir / "layer_vops.csv", outputs.vops, VOP_FIELDS)
    return files


def delimited_text_uri(path: Union[str, Path], crs: Optional[str] = None) -> str:
    """A QGIS ``delimitedtext`` provider URI for a layer CSV (points from x, y, z)."""
    uri = Path(path).resolve().as_uri() + "?type=csv&delimiter=,&xField=x&yField=y&zField=z&detectTypes=yes&geomType=point&spatialIndex=no&subsetIndex=no&watchFile=no"
    if crs:
        uri += f"&crs={crs}"
    return uri


# ----------------------------------------------------------------------------- one call


def register_pair(
    job: PairJob,
    cli: Union[None, str, Sequence[str]] = None,
    progress: Optional[ProgressCallback] = None,
    log: Optional[LogCallback] = None,
    cancelled: Optional[Callable[[], bool]] = None,
) -> HostOutputs:
    """Run ``forestreg register`` for ``job`` and read what it wrote (also the layer CSVs)."""
    Path(job.out_dir).mkdir(parents=True, exist_ok=True)
    run_cli(build_pair_command(job, cli), progress=progress, log=log, cancelled=cancelled)
    outputs = read_pair_outputs(job.out_dir, job.scanner_positions)
    if outputs.status == "ok":
        _need(Path(job.out_dir) / "transform.txt")
    write_layer_files(outputs)
    return outputs


def register_plot(
    job: PlotJob,
    cli: Union[None, str, Sequence[str]] = None,
    progress: Optional[ProgressCallback] = None,
    log: Optional[LogCallback] = None,
    cancelled: Optional[Callable[[], bool]] = None,
) -> HostOutputs:
    """Run ``forestreg plot`` for ``job`` and read what it wrote (also the layer CSV)."""
    Path(job.out_dir).mkdir(parents=True, exist_ok=True)
    run_cli(build_plot_command(job, cli), progress=progress, log=log, cancelled=cancelled)
    outputs = read_plot_outputs(job.out_dir)
    write_layer_files(outputs)
    return outputs
