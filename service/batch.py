"""Batches of many plots on Dask distributed (``forestreg batch``).

Every subfolder of ``PLOTS_DIR`` is one plot. With ``--command plot`` (the default) its scan files
are registered as ``forestreg plot`` would, into ``OUT/<plot>/``; the centre scan is the one named
in the folder's optional ``centre.txt``, else the plot command's default (the first scan in name
order), and a ``targets.csv`` in the folder is passed as ``--targets``. With ``--command trees`` or
``coregister`` a manifest CSV names each plot's inputs (``plot,cloud[,transform,field]`` or
``plot,ground,uav``; relative paths are looked up in ``PLOTS_DIR/<plot>/``, then beside the
manifest); ``trees`` also works without a manifest when each plot folder holds one cloud. With
``--command change`` each plot folder holds two surveys named ``before.*`` and ``after.*`` (clouds,
project files or trees tables), or a manifest names them (``plot,before,after``).

Each plot is one Dask task that runs the CLI in its own process (so a crash or a memory blow-up of
one plot costs only that plot), on a ``LocalCluster`` (``--workers N`` processes, one thread each)
or on an existing cluster (``--scheduler tcp://host:port``). ``OUT/summary.csv`` (one row per plot:
``plot,status,scans,registered,seconds,reason,...``) and ``OUT/index.html`` are rewritten after
every finished plot. A plot's row is also kept in ``OUT/<plot>/batch.json``, written last: a rerun
into the same ``OUT`` skips every plot that has one with status ``ok`` or ``failed`` (an honest
result), and runs again those that ended in ``error`` (bad input, crash) or never finished.

Status per plot: ``ok`` every scan registered (or the command succeeded), ``failed`` the command
ran to its end but could not register everything (exit 1, with the reason), ``error`` bad input
(exit 2) or a crash.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

from ..app.saved import SavedFileError, SavedPoses, SavedResult

log = logging.getLogger("forestreg.batch")

COMMANDS = ("plot", "trees", "coregister", "change")
SUMMARY_FIELDS = ["plot", "status", "scans", "registered", "seconds", "reason", "command", "exit_code", "trees", "worker", "resumed"]
PROCESSED = ("ok", "failed")
_NOT_SCANS = {"centre.txt", "center.txt", "targets.csv", "manifest.csv", "batch.json"}


@dataclass
class PlotTask:
    """One plot of a batch: the CLI arguments that process it and where they write."""

    name: str
    command: str
    args: list[str]
    out_dir: str
    inputs: int
    problem: str = ""  # set when the plot cannot run (no scans, bad manifest row): an error row


@dataclass
class BatchOutcome:
    rows: list[dict] = field(default_factory=list)
    summary: Optional[Path] = None
    overview: Optional[Path] = None
    seconds: float = 0.0
    workers: str = ""

    @property
    def complete(self) -> bool:
        """Every plot was processed (registered or honestly failed): a rerun has nothing to redo."""
        return all(r["status"] in PROCESSED for r in self.rows)

    @property
    def succeeded(self) -> bool:
        """Every plot succeeded (status ``ok``): the batch's exit status 0, else 1."""
        return all(r["status"] == "ok" for r in self.rows)

    def counts(self) -> dict[str, int]:
        """Plots per status ("ok", "failed", "error", ...)."""
        found: dict[str, int] = {}
        for r in self.rows:
            found[r["status"]] = found.get(r["status"], 0) + 1
        return found

    @property
    def resumed(self) -> int:
        """Plots done by an earlier run of the batch (skipped by this one)."""
        return sum(1 for r in self.rows if r.get("resumed"))

    @property
    def not_ok(self) -> list[str]:
        """The plots that did not succeed (``failed`` or ``error``), in name order."""
        return [r["plot"] for r in self.rows if r["status"] != "ok"]


# ----------------------------------------------------------------------------- discovering plots


def _scan_suffixes() -> tuple[str, ...]:
    from ..engine.io import SUPPORTED_READ_SUFFIXES

    return SUPPORTED_READ_SUFFIXES


def _read_manifest(path: Path) -> dict[str, dict]:
    from ..engine.core.errors import ParameterError

    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise ParameterError(f"cannot read the manifest {path}: {exc}") from None
    if not rows or "plot" not in rows[0]:
        raise ParameterError(f"{path}: a manifest needs a header with a 'plot' column and one row per plot")
    out: dict[str, dict] = {}
    for r in rows:
        name = (r.get("plot") or "").strip()
        if name:
            out[name] = {k.strip(): (v or "").strip() for k, v in r.items() if k}
    return out


def _resolve(value: str, plot_dir: Path, manifest_dir: Optional[Path]) -> str:
    p = Path(value).expanduser()
    if p.is_absolute():
        return str(p)
    for base in (plot_dir, manifest_dir):
        if base is not None and (base / p).exists():
            return str((base / p).resolve())
    return str((plot_dir / p).resolve())


def _product_folder(folder: Path) -> bool:
    """Whether ``folder`` is an output folder of forestreg (a batch's, a plot's, ...): not a plot."""
    from ..engine.core.atomic import MARKER

    return (folder / MARKER).is_file()


def _clouds_in(plot_dir: Path) -> list[Path]:
    """The point-cloud files of a plot folder in name order, told by their content (notes, tables
    and the folder's own centre.txt / targets.csv are not scans)."""
    from ..engine.io.sniff import is_point_cloud_file

    if not plot_dir.is_dir():
        return []
    suffixes = _scan_suffixes()
    return sorted(p for p in plot_dir.iterdir() if p.is_file() and p.suffix.lower() in suffixes
                  and p.name.lower() not in _NOT_SCANS and not p.name.startswith(".") and is_point_cloud_file(p))


def discover_plots(plots_dir: Path, out: Path, command: str = "plot", manifest: Optional[Path] = None, extra_args: Sequence[str] = ()) -> list[PlotTask]:
    """The plots of a batch, in name order (subfolders of ``plots_dir``, or the manifest's rows)."""
    from ..engine.core.errors import ParameterError

    if command not in COMMANDS:
        raise ParameterError(f"--command must be one of {', '.join(COMMANDS)}")
    if not plots_dir.is_dir():
        raise ParameterError(f"{plots_dir}: no such folder")
    if command == "coregister" and manifest is None:
        raise ParameterError("--command coregister needs --manifest (plot,ground,uav)")
    rows = _read_manifest(manifest) if manifest is not None else None
    manifest_dir = manifest.resolve().parent if manifest is not None else None
    out_resolved = out.resolve()
    names = sorted(rows) if rows is not None else sorted(
        p.name for p in plots_dir.iterdir() if p.is_dir() and not p.name.startswith(".") and p.resolve() != out_resolved
        and not _product_folder(p))
    if not names:
        raise ParameterError(f"{plots_dir}: no plot subfolders" + (" in the manifest" if rows is not None else ""))
    tasks = []
    for name in names:
        plot_dir = plots_dir / name
        target = str((out / name).resolve())
        task = PlotTask(name, command, [], target, 0)
        if command == "plot":
            scans = _clouds_in(plot_dir)
            if rows is not None and rows[name].get("scans"):
                scans = [Path(_resolve(s, plot_dir, manifest_dir)) for s in rows[name]["scans"].split(";") if s.strip()]
            task.inputs = len(scans)
            if len(scans) < 2:
                task.problem = f"{len(scans)} scan file(s) in {plot_dir}: a plot needs at least two"
            else:
                task.args = ["plot", *[str(s.resolve()) for s in scans], "--out", target]
                centre = (rows or {}).get(name, {}).get("centre", "")
                if not centre:
                    for fname in ("centre.txt", "center.txt"):
                        if (plot_dir / fname).is_file():
                            centre = next((l.strip() for l in (plot_dir / fname).read_text(encoding="utf-8").splitlines() if l.strip()), "")
                            break
                if centre:
                    if not any(Path(s).name == Path(centre).name for s in scans):
                        task.problem = f"centre scan {centre!r} is not among the plot's scans"
                    task.args += ["--centre", Path(centre).name]
                if (plot_dir / "targets.csv").is_file():
                    task.args += ["--targets", str((plot_dir / "targets.csv").resolve())]
        elif command == "trees":
            row = (rows or {}).get(name, {})
            if row.get("cloud"):
                cloud = _resolve(row["cloud"], plot_dir, manifest_dir)
            else:
                clouds = _clouds_in(plot_dir)
                cloud = str(clouds[0].resolve()) if len(clouds) == 1 else ""
                if not cloud:
                    task.problem = f"{len(clouds)} clouds in {plot_dir}: name the cloud in a manifest (plot,cloud)"
            task.inputs = 1
            task.args = ["trees", cloud, "--out", target]
            for key, option in (("transform", "--transform"), ("field", "--field")):
                if row.get(key):
                    task.args += [option, _resolve(row[key], plot_dir, manifest_dir)]
        elif command == "change":
            row = (rows or {}).get(name, {})
            pair = []
            for role in ("before", "after"):
                if row.get(role):
                    pair.append(_resolve(row[role], plot_dir, manifest_dir))
                    continue
                found = sorted(p for p in plot_dir.iterdir() if p.stem.lower() == role and not p.name.startswith(".")) if plot_dir.is_dir() else []
                pair.append(str(found[0].resolve()) if len(found) == 1 else "")
                if len(found) != 1 and not task.problem:
                    task.problem = f"{len(found)} files named {role}.* in {plot_dir}: name the surveys in a manifest (plot,before,after)"
            task.inputs = 2
            task.args = ["change", *pair, "--out", target]
        else:
            row = rows[name]
            if not row.get("ground") or not row.get("uav"):
                task.problem = "the manifest row needs 'ground' and 'uav'"
            task.inputs = 2
            task.args = ["coregister", _resolve(row.get("ground", ""), plot_dir, manifest_dir),
                         _resolve(row.get("uav", ""), plot_dir, manifest_dir), "--out", target]
        task.args += list(extra_args)
        tasks.append(task)
    from .jobs import ArgumentError, validate_args

    for task in tasks:  # the CLI's own parser, before any plot runs (e.g. a wrong --extra)
        if not task.problem:
            try:
                validate_args(task.args)
            except ArgumentError as exc:
                raise ParameterError(f"plot {task.name}: {str(exc).split('error: ', 1)[-1]}") from None
    return tasks


# ----------------------------------------------------------------------------- one plot (a Dask task)


def _read_json(path: Path) -> Optional[dict]:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _read_saved(kind, path: Path):
    """A saved file read as ``kind`` (:class:`~forestreg.app.saved.SavedResult` or
    :class:`~forestreg.app.saved.SavedPoses`), or None when it is missing or unreadable."""
    try:
        return kind.read(path)
    except SavedFileError:
        return None


def _last_error(text: str) -> str:
    lines = [l.strip() for l in text.splitlines() if l.strip() and not l.lstrip().startswith("{")]
    for line in reversed(lines):
        if "error:" in line:
            return line.split("error:", 1)[1].strip()
    return lines[-1] if lines else ""


def run_plot(task: dict) -> dict:
    """Process one plot in a CLI subprocess and return its summary row (never raises)."""
    from ..engine.core.atomic import write_text_atomic
    from .jobs import _package_env

    t = PlotTask(**task)
    row = {"plot": t.name, "status": "error", "scans": t.inputs, "registered": "", "seconds": 0.0, "reason": "",
           "command": t.command, "exit_code": "", "trees": "", "worker": os.uname().nodename if hasattr(os, "uname") else "", "resumed": 0}
    if t.problem:
        row["reason"] = t.problem
        return row
    t0 = time.perf_counter()
    try:
        run = subprocess.run([sys.executable, "-m", "forestreg.cli", *t.args, "--quiet"], stdin=subprocess.DEVNULL, capture_output=True, text=True, env=_package_env())
        code, stderr = run.returncode, run.stderr
    except OSError as exc:
        code, stderr = -1, f"error: cannot start the CLI: {exc}"
    row["seconds"] = round(time.perf_counter() - t0, 2)
    row["exit_code"] = code
    out = Path(t.out_dir)
    if code in (0, 1):
        row["status"] = "ok" if code == 0 else "failed"
        if t.command == "plot":
            poses = _read_saved(SavedPoses, out / "poses.json") or SavedPoses("")
            row["scans"] = len(poses.scans) or t.inputs
            row["registered"] = len(poses.scans) - len(poses.not_registered)
            row["reason"] = poses.reason()
        elif t.command in ("coregister", "change"):
            result = _read_saved(SavedResult, out / "result.json")
            row["registered"] = 1 if result is not None and result.ok else 0
            row["reason"] = result.reason if result is not None else ""
            if t.command == "change" and result is not None and result.trees:
                row["trees"] = sum(result.trees.values())
        else:
            try:
                with (out / "trees.csv").open(newline="", encoding="utf-8") as fh:
                    row["trees"] = sum(1 for _ in csv.DictReader(fh))
            except OSError:
                pass
        if code == 1 and not row["reason"]:
            row["reason"] = _last_error(stderr)
    else:
        row["reason"] = _last_error(stderr) or f"the command stopped with exit status {code}"
    if out.is_dir() and code != 130:  # an interrupted plot is not finished: no batch.json, a rerun runs it
        write_text_atomic(out / "batch.json", json.dumps(row, indent=2) + "\n")
    return row


# ----------------------------------------------------------------------------- the batch


def _write_summary(out: Path, rows: list[dict], facts: dict) -> tuple[Path, Path]:
    from ..engine.core.atomic import write_text_atomic
    from ..engine.report.batch_report import write_batch_report

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_FIELDS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in sorted(rows, key=lambda r: r["plot"]):
        w.writerow(r)
    summary = out / "summary.csv"
    write_text_atomic(summary, buf.getvalue())
    try:
        overview = write_batch_report(rows, out, title=f"forestreg batch: {out.name}", facts=facts)
    except Exception as exc:  # an overview must never lose the summary
        log.warning("could not write the overview: %s", exc)
        overview = out / "index.html"
    return summary, overview


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM) during a batch: ``done`` of ``total`` plots finished; their folders and
    rows in ``OUT/summary.csv`` are kept, and a rerun into ``out`` resumes the others."""

    def __init__(self, done: int, total: int, out: Path) -> None:
        super().__init__(f"interrupted: {done} of {total} plots finished and kept in {out} (summary.csv); "
                         f"a rerun into {out} runs the others")
        self.done, self.total, self.out = done, total, out


def _client(workers: Optional[int], scheduler: Optional[str]):
    from dask.distributed import Client, LocalCluster

    if not log.isEnabledFor(logging.INFO):  # Dask's own INFO lines only with forestreg -v
        logging.getLogger("distributed").setLevel(logging.WARNING)
    if scheduler:
        return Client(scheduler, timeout="30s"), None
    n = workers or max(1, (os.cpu_count() or 2))
    # The worker processes start with Ctrl-C ignored: a Ctrl-C in the terminal reaches the whole
    # process group, and the batch (not each worker, with a traceback) stops them; each plot's CLI
    # still honours it (FORESTREG_INTERRUPTIBLE) and leaves its folder complete or resumable. The
    # workers log only what loses work: a heartbeat to a scheduler closing at the end of the batch
    # is no error of the batch (it printed a traceback).
    import signal
    import threading

    ignore = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if ignore else None
    try:
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=logging.CRITICAL)
    finally:
        if ignore:
            signal.signal(signal.SIGINT, previous)
    return Client(cluster), cluster


def run_batch(
    plots_dir: Path,
    out: Path,
    *,
    workers: Optional[int] = None,
    scheduler: Optional[str] = None,
    command: str = "plot",
    manifest: Optional[Path] = None,
    extra_args: Sequence[str] = (),
    progress: Optional[Callable[[float, str], None]] = None,
) -> BatchOutcome:
    """Process every plot of ``plots_dir`` into ``out`` on Dask; resumes a previous run."""
    from ..engine.core.atomic import MARKER, check_output_folder

    t0 = time.perf_counter()
    plots_dir, out = Path(plots_dir), Path(out)
    tasks = discover_plots(plots_dir, out, command, manifest, extra_args)
    check_output_folder(out, "batch", inputs=[plots_dir])  # never mix a batch into a folder of other files
    out.mkdir(parents=True, exist_ok=True)
    if not (out / MARKER).is_file():
        (out / MARKER).write_text("batch\n", encoding="utf-8")
    rows: dict[str, dict] = {}
    todo: list[PlotTask] = []
    for task in tasks:
        previous = _read_json(Path(task.out_dir) / "batch.json")
        if previous and previous.get("status") in PROCESSED and previous.get("command", command) == command:
            previous["resumed"] = 1
            rows[task.name] = previous
        else:
            todo.append(task)
    report = progress or (lambda f, m: None)
    total = len(tasks)
    report(len(rows) / total, f"{len(rows)} of {total} plots already done, {len(todo)} to run")
    outcome = BatchOutcome()
    facts: dict = {"command": command}
    if todo:
        from dask.distributed import as_completed

        client, cluster = _client(workers, scheduler)
        try:
            n_workers = len(client.scheduler_info().get("workers", {}))
            outcome.workers = scheduler or f"local cluster, {n_workers} workers"
            facts["workers"] = outcome.workers
            futures = {client.submit(run_plot, asdict(t), key=f"forestreg-plot-{t.name}-{time.time_ns()}", pure=False): t for t in todo}
            for future in as_completed(futures):
                task = futures[future]
                try:
                    row = future.result()
                except Exception as exc:  # the worker died (e.g. killed by its memory limit)
                    row = {"plot": task.name, "status": "error", "scans": task.inputs, "registered": "", "seconds": "",
                           "reason": f"the task was lost: {type(exc).__name__}: {exc}", "command": command, "exit_code": "", "resumed": 0}
                rows[task.name] = row
                facts["seconds"] = f"{time.perf_counter() - t0:.1f}"
                _write_summary(out, list(rows.values()), facts)
                report(len(rows) / total, f"{task.name}: {row['status']}")
        except KeyboardInterrupt:
            raise BatchInterrupted(len(rows), total, out) from None
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    outcome.seconds = time.perf_counter() - t0
    facts["seconds"] = f"{outcome.seconds:.1f}"
    outcome.rows = sorted(rows.values(), key=lambda r: r["plot"])
    outcome.summary, outcome.overview = _write_summary(out, outcome.rows, facts)
    return outcome
