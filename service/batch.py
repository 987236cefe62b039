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
or on an existing cluster (``--scheduler tcp://host:port``). The plot's process runs ``--threads``
threads (default: the usable cores shared out among the local workers, 1 on an existing cluster):
the numerical thread pools (OpenMP, BLAS, Numba, forestreg's own) are sized by environment
variables, so N workers keep N cores busy and no more. The process dies with its worker (a worker
killed or lost takes its plot's process along: no orphan writes into ``OUT``); Dask then runs the
plot again on another worker, and its row says so (``attempts``, ``retried_after``). A ``plot``
stopped half-way (worker lost, batch killed) resumes from the links its project file kept
(``project run``); one that cannot is started over in an emptied folder. Its peak
memory (``peak_mb``, the process tree's high-water mark) and CPU time are in its row; with
``--memory-limit`` a plot whose processes outgrow the limit is stopped (an ``error`` row with the
peak) and the local workers get the same limit.

``OUT/summary.csv`` (one row per plot: ``plot,status,scans,registered,seconds,reason,...``) and
``OUT/index.html`` are rewritten as plots finish (spaced to stay under 5% of the time: the rewrite
of 1,000 rows costs about 20 ms, so it runs at most about twice a second) and always at the end. A plot's row is also kept in ``OUT/<plot>/batch.json``, written last:
a rerun into the same ``OUT`` skips every plot that has one with status ``ok`` or ``failed`` (an
honest result), and runs again those that ended in ``error`` (bad input, crash) or never finished.

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
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

from ..app.saved import SavedFileError, SavedPoses, SavedProject, SavedResult
from ..engine.report.batch_report import LINKED_OUTPUTS

log = logging.getLogger("forestreg.batch")

COMMANDS = ("plot", "trees", "coregister", "change")
SUMMARY_FIELDS = [
    "plot",
    "status",
    "scans",
    "registered",
    "seconds",
    "reason",
    "command",
    "exit_code",
    "trees",
    "worker",
    "resumed",
    "peak_mb",
    "cpu_s",
    "threads",
    "attempts",
    "retried_after",
]
PROCESSED = ("ok", "failed")
_NOT_SCANS = {"centre.txt", "center.txt", "targets.csv", "manifest.csv", "batch.json"}
#: Environment variables that size the numerical thread pools of a plot's process (OpenMP for
#: Open3D, the BLAS libraries, Numba, NumExpr, and forestreg's own block pool).
THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "NUMBA_NUM_THREADS",
    "RAYON_NUM_THREADS",
    "FORESTREG_THREADS",
)
#: The folder of ``OUT`` where each plot's attempts are noted (one small JSON file per plot).
ATTEMPTS_DIR = ".forestreg-batch"
#: Seconds between two checks of a running plot's exit.
_POLL_S = 0.1
#: Seconds between two samples of a running plot's memory under --memory-limit (the resident
#: memory of its process tree): a plot that outgrows the limit for longer than this is stopped.
MEMORY_SAMPLE_S = 0.05
#: Dask settings of the batch's own local cluster (an existing cluster keeps its own): no stack
#: sampling, system monitor and memory check once a second, no replica balancing. Its workers
#: only wait for plot processes (the plots' memory is watched by the batch itself).
LOCAL_CLUSTER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.system-monitor.interval": "1s",
    "distributed.admin.system-monitor.disk": False,
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.scheduler.active-memory-manager.start": False,
}


@dataclass
class PlotTask:
    """One plot of a batch: the CLI arguments that process it and where they write."""

    name: str
    command: str
    args: list[str]
    out_dir: str
    inputs: int
    problem: str = ""  # set when the plot cannot run (no scans, bad manifest row): an error row
    threads: int = 1  # threads of the plot's process (its numerical thread pools)
    memory_limit: int = 0  # bytes the plot's process tree may hold; 0: no limit
    run: str = ""  # the batch run this task belongs to (tells a retry from a resumed plot)
    #: ``plot``: its scan files (resolved) and the ``project run`` arguments that finish it from
    #: the project file a stopped attempt saved (None: its options need a start from scratch);
    #: both read from the arguments as the command line parses them (:func:`discover_plots`)
    scans: list[str] = field(default_factory=list)
    resume: Optional[list[str]] = None


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
    from ..engine.core.errors import InvalidArgumentError, ParameterError
    from ..engine.core.names import safe_name, same_name_key

    rows: list[tuple[int, dict]] = []  # (the row's number as a spreadsheet shows it: the header is row 1, its fields)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            line = 1
            for r in reader:
                rows.append((line + 1, r))
                line = reader.line_num
    except OSError as exc:
        raise ParameterError(f"cannot read the manifest {path}: {exc}") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise ParameterError(f"{path}: not a readable CSV manifest ({exc})") from None
    if not rows or "plot" not in rows[0][1]:
        raise ParameterError(f"{path}: a manifest needs a header with a 'plot' column and one row per plot")
    # Each name becomes the folder OUT/<plot> (and OUT/<plot>.json files): one plain name, checked
    # before any work, never dropped, never shared by two rows (one would silently replace the other).
    out: dict[str, dict] = {}
    seen: dict[str, tuple[str, list[int]]] = {}
    for number, row in rows:
        cells = {k.strip(): (v or "").strip() for k, v in row.items() if isinstance(k, str) and k.strip()}
        if not any(cells.values()) and not any(row.get(None) or ()):
            continue  # a row of separators only (a spreadsheet's trailing rows): no plot
        name = (row.get("plot") or "").strip()
        try:
            safe_name(name, f"{path} row {number}: plot")
        except InvalidArgumentError as exc:
            raise ParameterError(str(exc)) from None
        seen.setdefault(same_name_key(name), (name, []))[1].append(number)
        out[name] = cells
    for key, (first, numbers) in seen.items():
        if len(numbers) > 1:
            names = sorted({n for n in out if same_name_key(n) == key})
            if len(names) == 1:
                raise ParameterError(
                    f"{path}: plot {first!r} is named in rows {_and(numbers)}: give each plot its own name"
                )
            raise ParameterError(
                f"{path}: plots {_and([repr(n) for n in names])} (rows {_and(numbers)}) differ only in case or "
                "accents: they would be one folder on macOS and Windows; give each plot its own name"
            )
    return out


def _and(items) -> str:
    items = [str(i) for i in items]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


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
    return sorted(
        p
        for p in plot_dir.iterdir()
        if p.is_file()
        and p.suffix.lower() in suffixes
        and p.name.lower() not in _NOT_SCANS
        and not p.name.startswith(".")
        and is_point_cloud_file(p)
    )


def discover_plots(
    plots_dir: Path, out: Path, command: str = "plot", manifest: Optional[Path] = None, extra_args: Sequence[str] = ()
) -> list[PlotTask]:
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
    names = (
        sorted(rows)
        if rows is not None
        else sorted(
            p.name
            for p in plots_dir.iterdir()
            if p.is_dir() and not p.name.startswith(".") and p.resolve() != out_resolved and not _product_folder(p)
        )
    )
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
                            centre = next(
                                (
                                    l.strip()
                                    for l in (plot_dir / fname).read_text(encoding="utf-8").splitlines()
                                    if l.strip()
                                ),
                                "",
                            )
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
                found = (
                    sorted(p for p in plot_dir.iterdir() if p.stem.lower() == role and not p.name.startswith("."))
                    if plot_dir.is_dir()
                    else []
                )
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
            task.args = [
                "coregister",
                _resolve(row.get("ground", ""), plot_dir, manifest_dir),
                _resolve(row.get("uav", ""), plot_dir, manifest_dir),
                "--out",
                target,
            ]
        task.args += list(extra_args)
        tasks.append(task)
    from .jobs import ArgumentError, validate_args

    for task in tasks:  # the CLI's own parser, before any plot runs (e.g. a wrong --extra)
        if not task.problem:
            try:
                parsed = validate_args(task.args)
            except ArgumentError as exc:
                raise ParameterError(f"plot {task.name}: {str(exc).split('error: ', 1)[-1]}") from None
            if command == "plot":
                task.scans = [str(Path(s).resolve()) for s in parsed.scans]
                task.resume = parsed.project_run_args(parsed, Path(task.out_dir) / "project.json")
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


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """The plot's process gets SIGKILL when the worker thread that started it ends (the worker
    killed, lost or restarted): no orphan keeps writing into ``OUT`` while Dask runs the plot again
    elsewhere. Linux only; elsewhere a no-op."""
    if _PRCTL is not None:
        _PRCTL(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def _load_prctl():
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_PRCTL = _load_prctl()


_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def _proc_tree_rss(pid: int) -> Optional[int]:
    """:func:`_tree_rss` from Linux's ``/proc`` (each process's ``task/*/children`` and ``statm``):
    a few reads per process of the tree, whatever the number of processes on the machine (sampled
    20 times a second); None where ``/proc`` has no ``children`` files."""
    if not os.path.exists(f"/proc/{pid}/task/{pid}/children"):
        return None
    total, todo, seen = 0, [pid], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            with open(f"/proc/{p}/statm", "rb") as fh:
                total += int(fh.read().split()[1]) * _PAGE
            tasks = os.listdir(f"/proc/{p}/task")
        except (OSError, ValueError, IndexError):
            continue  # ended meanwhile
        for t in tasks:
            try:
                with open(f"/proc/{p}/task/{t}/children", "rb") as fh:
                    todo.extend(int(c) for c in fh.read().split())
            except (OSError, ValueError):
                pass
    return total


def _tree_rss(pid: int) -> int:
    """Resident bytes of the process ``pid`` and its descendants (0 when it is gone)."""
    fast = _proc_tree_rss(pid) if sys.platform.startswith("linux") else None
    if fast is not None:
        return fast
    import psutil

    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.Error:
        return 0
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def _kill_tree(pid: int) -> None:
    import psutil

    try:
        root = psutil.Process(pid)
        procs = [*root.children(recursive=True), root]
    except psutil.Error:
        return
    for p in procs:
        try:
            p.kill()
        except psutil.Error:
            pass


def _remove_leftovers(out: Path) -> None:
    """Remove the temporary folders an attempt of this plot left beside ``OUT/<plot>`` when its
    process was killed (a folder transaction never finished: the plot's folder itself is the
    earlier complete one or absent)."""
    from ..engine.core.atomic import unfinished_outputs

    for entry in unfinished_outputs(out.parent, out):
        shutil.rmtree(entry, ignore_errors=True)


def _remove_unfinished(out: Path) -> None:
    """Remove ``OUT/<plot>`` before the ``plot`` command starts it over (nothing to resume), and
    after it was stopped over its memory limit: the command fills its folder in place (the others
    write theirs by one rename), so no product of an earlier attempt is mixed into the new one. Only
    a folder of forestreg's ``plot`` (its marker file) is removed."""
    from ..engine.core.atomic import MARKER

    try:
        kind = (out / MARKER).read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError):
        return
    if kind == "plot":
        shutil.rmtree(out, ignore_errors=True)


def _resume_args(t: PlotTask) -> Optional[tuple[list[str], int, int]]:
    """``project run`` arguments that finish a plot an earlier attempt left unfinished (its
    project file in ``OUT/<plot>`` saved after every link, no ``batch.json``), keeping the links
    that attempt registered: (arguments, links done, links); None when there is nothing to resume
    (no such folder, other scans, no link done) or the plot's options need a start from scratch
    (``t.resume`` None: see :func:`discover_plots`)."""
    from ..engine.core.atomic import MARKER

    out = Path(t.out_dir)
    if t.resume is None:
        return None
    try:
        if (out / MARKER).read_text(encoding="utf-8").strip() != "plot" or (out / "batch.json").exists():
            return None
    except (OSError, UnicodeDecodeError):
        return None
    try:
        project = SavedProject.read(out / "project.json")
    except SavedFileError:
        return None
    done = project.links_ok
    if {str(s.path) for s in project.scans} != set(t.scans) or not done:
        return None
    return list(t.resume), done, len(project.link_statuses)


def _note_attempt(t: PlotTask, worker: str) -> tuple[int, str]:
    """Note this attempt in ``OUT/.forestreg-batch/<plot>.json``; returns (attempts of this run so
    far, including this one; why the previous attempt did not finish, "" for a first attempt)."""
    from ..engine.core.atomic import write_text_atomic

    folder = Path(t.out_dir).parent / ATTEMPTS_DIR
    path = folder / f"{t.name}.json"
    earlier = (_read_json(path) or {}).get("attempts", []) if path.is_file() else []
    earlier = [a for a in earlier if isinstance(a, dict)]
    mine = [a for a in earlier if a.get("run") == t.run]
    reason = ""
    last = earlier[-1] if earlier else None
    if last is not None and not last.get("finished"):  # the last attempt never came to its end
        if last.get("run") == t.run:
            reason = f"worker lost ({last.get('worker') or 'unknown worker'})"
        else:
            reason = "an earlier batch stopped during the plot"
    entry = {"run": t.run, "worker": worker, "pid": os.getpid(), "started": time.time()}
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps({"attempts": (earlier + [entry])[-20:]}, indent=1) + "\n")
    except OSError as exc:
        log.warning("could not note the attempt of plot %s: %s", t.name, exc)
    return len(mine) + 1, reason


def _finish_attempt(t: PlotTask) -> None:
    """Note in ``OUT/.forestreg-batch/<plot>.json`` that this process's attempt came to its end."""
    from ..engine.core.atomic import write_text_atomic

    path = Path(t.out_dir).parent / ATTEMPTS_DIR / f"{t.name}.json"
    attempts = (_read_json(path) or {}).get("attempts", [])
    for a in reversed(attempts):
        if isinstance(a, dict) and a.get("run") == t.run and a.get("pid") == os.getpid():
            a["finished"] = True
            try:
                write_text_atomic(path, json.dumps({"attempts": attempts}, indent=1) + "\n")
            except OSError as exc:
                log.warning("could not note the end of plot %s: %s", t.name, exc)
            return


def _worker_name() -> str:
    try:
        from dask.distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return os.uname().nodename if hasattr(os, "uname") else ""


def plot_environment(threads: int) -> dict[str, str]:
    """The environment of a plot's process: the package importable, every numerical thread pool
    sized to ``threads`` (a user's own values of these variables are replaced)."""
    from .jobs import _package_env

    env = _package_env()
    for name in THREAD_VARIABLES:
        env[name] = str(max(1, int(threads)))
    return env


def _run_cli(args: list[str], threads: int, memory_limit: int) -> tuple[int, str, float, float, float]:
    """Run ``forestreg ARGS --quiet``; returns (exit code, stderr, peak MB of the process tree,
    CPU seconds, peak MB when it was stopped over ``memory_limit`` else 0)."""
    with tempfile.TemporaryFile(mode="w+b") as err:
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "forestreg.cli", *args, "--quiet"],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=err,
                env=plot_environment(threads),
                preexec_fn=_die_with_parent if _PRCTL is not None else None,
            )
        except OSError as exc:
            return -1, f"error: cannot start the CLI: {exc}", 0.0, 0.0, 0.0
        over = sampled = 0.0
        usage = None
        # under a limit the tree's memory is sampled every MEMORY_SAMPLE_S from the start (a plot
        # of a second or two is stopped too); without one every 0.5 s after the first second,
        # for the peak of the whole tree
        interval = MEMORY_SAMPLE_S if memory_limit else 0.5
        next_check = time.monotonic() + (0.0 if memory_limit else 1.0)
        try:
            while True:
                if hasattr(os, "wait4"):
                    pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                    if pid:
                        proc.returncode = os.waitstatus_to_exitcode(status)
                        break
                elif proc.poll() is not None:  # Windows: no rusage of a child; its memory sampled
                    break
                if (memory_limit or usage is None) and time.monotonic() >= next_check:
                    next_check = time.monotonic() + interval
                    rss = _tree_rss(proc.pid)
                    sampled = max(sampled, rss / 1e6)
                    if memory_limit and rss > memory_limit and not over:
                        over = rss / 1e6
                        _kill_tree(proc.pid)
                time.sleep(min(_POLL_S, interval))
        except BaseException:
            _kill_tree(proc.pid)  # the worker thread stops (interrupt): the plot stops with it
            raise
        code = proc.returncode
        err.seek(0)
        stderr = err.read().decode("utf-8", "replace")
    if usage is None:
        return code, stderr, sampled, 0.0, over
    # ru_maxrss: KiB on Linux, bytes on macOS; the process and the children it waited for (its tree)
    peak = usage.ru_maxrss / 1024.0 if sys.platform.startswith("linux") else usage.ru_maxrss / 1e6
    return code, stderr, max(peak, sampled), usage.ru_utime + usage.ru_stime, over


def run_plot(task: dict) -> dict:
    """Process one plot in a CLI subprocess and return its summary row (never raises)."""
    from ..engine.core.atomic import write_text_atomic

    t = PlotTask(**task)
    worker = _worker_name()
    row = {
        "plot": t.name,
        "status": "error",
        "scans": t.inputs,
        "registered": "",
        "seconds": 0.0,
        "reason": "",
        "command": t.command,
        "exit_code": "",
        "trees": "",
        "worker": worker,
        "resumed": 0,
        "peak_mb": "",
        "cpu_s": "",
        "threads": t.threads,
        "attempts": 1,
        "retried_after": "",
        "run": t.run,
    }
    if t.problem:
        row["reason"] = t.problem
        return row
    out = Path(t.out_dir)
    previous = _read_json(out / "batch.json")
    if previous and previous.get("run") == t.run and t.run:  # finished in this run; its result was lost with its worker
        return previous
    row["attempts"], row["retried_after"] = _note_attempt(t, worker)
    if row["attempts"] > 1 or row["retried_after"]:
        _remove_leftovers(out)
    args = t.args
    if t.command == "plot":
        resume = _resume_args(t)  # an attempt stopped after some links: they are kept
        if resume is not None:
            args, done, total_links = resume
            note = f"resumed with {done} of {total_links} links done"
            row["retried_after"] = f"{row['retried_after']}; {note}" if row["retried_after"] else note
        else:
            _remove_unfinished(out)
    t0 = time.perf_counter()
    code, stderr, peak, cpu, over = _run_cli(args, t.threads, t.memory_limit)
    row["seconds"] = round(time.perf_counter() - t0, 2)
    row["exit_code"] = code
    row["peak_mb"], row["cpu_s"] = round(peak, 1), round(cpu, 2)
    if over or code == 130:  # stopped (over the limit, interrupted): not finished, no batch.json, a rerun runs it
        _remove_leftovers(out)
        if t.command == "plot":
            _remove_unfinished(out)
        if over:
            row["reason"] = (
                f"stopped over the memory limit: its processes held {over:.0f} MB, the limit is "
                f"{t.memory_limit / 1e6:.0f} MB per worker (--memory-limit)"
            )
            _finish_attempt(t)
        else:  # interrupted: unfinished, a rerun says an earlier batch stopped during it
            row["reason"] = _last_error(stderr) or "interrupted"
        return row
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
    if t.memory_limit and peak * 1e6 > t.memory_limit:  # a spike shorter than the sampling interval
        note = (
            f"its peak of {peak:.0f} MB passed the memory limit ({t.memory_limit / 1e6:.0f} MB) between two samples "
            f"(every {MEMORY_SAMPLE_S:g} s), too briefly to be stopped"
        )
        row["reason"] = f"{row['reason']}; {note}" if row["reason"] else note
    row["outputs"] = [
        name for name in LINKED_OUTPUTS if (out / name).is_file()
    ]  # for the overview: no stat per row later
    if out.is_dir():
        write_text_atomic(out / "batch.json", json.dumps(row, indent=2) + "\n")
    _finish_attempt(t)
    return row


# ----------------------------------------------------------------------------- the batch


def _write_summary(out: Path, rows: list[dict], facts: dict, *, interrupted: bool = False) -> tuple[Path, Path]:
    """Write ``summary.csv``, then the overview ``index.html`` (whose failure never loses the
    summary: said on stderr, or only with -v after Ctrl-C, which may have stopped the overview's
    first import half-way and left its modules unusable)."""
    from ..engine.core.atomic import write_text_atomic

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_FIELDS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in sorted(rows, key=lambda r: r["plot"]):
        w.writerow(r)
    summary = out / "summary.csv"
    write_text_atomic(summary, buf.getvalue())
    try:
        from ..engine.report.batch_report import write_batch_report

        overview = write_batch_report(rows, out, title=f"forestreg batch: {out.name}", facts=facts)
    except Exception as exc:  # an overview must never lose the summary
        (log.info if interrupted else log.warning)("could not write the overview: %s", exc)
        overview = out / "index.html"
    return summary, overview


class _Summary:
    """Writes ``summary.csv`` and ``index.html`` as plots finish, spaced so that the rewrites (each
    O(plots)) stay a small share of the batch's time: the next one waits at least 20 times the last
    one's duration (a 1,000-plot batch: a rewrite of about 20 ms, so at most about two a second)."""

    def __init__(self, out: Path, facts: dict, share: float = 0.05) -> None:
        self.out, self.facts, self.share = out, facts, share
        self.next_at = 0.0
        self.writes = 0
        self.seconds = 0.0

    def update(self, rows: list[dict], *, force: bool = False, interrupted: bool = False) -> None:
        now = time.perf_counter()
        if not force and now < self.next_at:
            return
        _write_summary(self.out, rows, self.facts, interrupted=interrupted)
        spent = time.perf_counter() - now
        self.writes += 1
        self.seconds += spent
        self.next_at = time.perf_counter() + spent / self.share


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM) during a batch: ``done`` of ``total`` plots finished; their folders and
    rows in ``OUT/summary.csv`` are kept, and a rerun into ``out`` resumes the others."""

    def __init__(self, done: int, total: int, out: Path) -> None:
        super().__init__(
            f"interrupted: {done} of {total} plots finished and kept in {out} (summary.csv); "
            f"a rerun into {out} runs the others"
        )
        self.done, self.total, self.out = done, total, out


def _client(workers: Optional[int], scheduler: Optional[str], memory_limit: int = 0):
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

    import dask

    ignore = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if ignore else None
    try:
        # The local workers hold no data: each runs one plot process at a time and waits for it.
        # Dask's instruments for data-holding workers (a stack sampler every 10 ms, replica
        # balancing every 2 s, a memory check every 100 ms) only take CPU from the plots.
        with dask.config.set(LOCAL_CLUSTER_CONFIG):
            # no dashboard; the scheduler's own HTTP server (health, metrics) on a free loopback
            # port: its default, 8787 on every interface, is taken by a second batch on the
            # machine, and Dask then warned on stderr
            cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                silence_logs=logging.CRITICAL,
                memory_limit=memory_limit or "auto",
            )
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
    threads: Optional[int] = None,
    memory_limit: int = 0,
) -> BatchOutcome:
    """Process every plot of ``plots_dir`` into ``out`` on Dask; resumes a previous run.

    ``threads``: threads of each plot's process (default: the usable cores shared out among the
    local workers; 1 on an existing cluster). ``memory_limit``: bytes per worker (0: none): the
    local workers' Dask memory limit, and the most a plot's processes may hold before the plot is
    stopped (an ``error`` row)."""
    from ..engine.core.atomic import MARKER, check_output_folder
    from ..engine.core.errors import ParameterError

    t0 = time.perf_counter()
    plots_dir, out = Path(plots_dir), Path(out)
    if threads is not None and threads < 1:
        raise ParameterError("--threads must be at least 1")
    if memory_limit < 0:
        raise ParameterError("--memory-limit must be positive")
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
    summary = _Summary(out, facts)
    if todo:
        from dask.distributed import as_completed

        client, cluster = _client(workers, scheduler, memory_limit)
        try:
            n_workers = len(client.scheduler_info().get("workers", {}))
            if threads is None:
                threads = 1 if scheduler else max(1, _usable_cores() // max(1, n_workers))
            outcome.workers = scheduler or f"local cluster, {n_workers} workers"
            facts["workers"] = outcome.workers
            facts["threads per plot"] = threads
            if memory_limit:
                facts["memory limit per worker"] = f"{memory_limit / 1e6:.0f} MB"
            run_id = f"{time.time_ns():x}-{os.getpid()}"
            # A plot whose worker dies (killed, lost, over Dask's memory limit) is run again on
            # another worker by the scheduler itself, up to distributed.scheduler.allowed-failures
            # times (default 3); run_plot never raises, so there is nothing for retries= to redo.
            # the largest plots (by their input files) start first: the batch does not end waiting
            # for one large plot started last while the other workers sit idle
            futures = {}
            for rank, t in enumerate(sorted(todo, key=lambda t: -_input_bytes(t))):
                t.threads, t.memory_limit, t.run = threads, memory_limit, run_id
                futures[
                    client.submit(
                        run_plot,
                        asdict(t),
                        key=f"forestreg-plot-{t.name}-{run_id}",
                        pure=False,
                        retries=0,
                        priority=len(todo) - rank,
                    )
                ] = t
            for future in as_completed(futures):
                task = futures[future]
                try:
                    row = future.result()
                except Exception as exc:  # the worker died every time it ran the plot (e.g. its memory)
                    reason = (
                        f"every worker that ran it died ({exc})"
                        if type(exc).__name__ == "KilledWorker"
                        else f"the task was lost: {type(exc).__name__}: {exc}"
                    )
                    row = {
                        "plot": task.name,
                        "status": "error",
                        "scans": task.inputs,
                        "registered": "",
                        "seconds": "",
                        "reason": reason,
                        "command": command,
                        "exit_code": "",
                        "resumed": 0,
                        "threads": threads,
                        "retried_after": "worker lost",
                    }
                rows[task.name] = row
                facts["seconds"] = f"{time.perf_counter() - t0:.1f}"
                summary.update(list(rows.values()))
                report(len(rows) / total, f"{task.name}: {row['status']}")
        except KeyboardInterrupt:
            summary.update(list(rows.values()), force=True, interrupted=True)
            raise BatchInterrupted(len(rows), total, out) from None
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    outcome.seconds = time.perf_counter() - t0
    facts["seconds"] = f"{outcome.seconds:.1f}"
    outcome.rows = sorted(rows.values(), key=lambda r: r["plot"])
    outcome.summary, outcome.overview = _write_summary(out, outcome.rows, facts)
    log.info("summary rewritten %d times in %.2f s", summary.writes + 1, summary.seconds)
    return outcome


def _input_bytes(task: PlotTask) -> int:
    """Bytes of the plot's input files (its scans or clouds): a measure of its work."""
    total = 0
    for a in task.args:
        if a.startswith("-") or a == task.out_dir:
            continue
        try:
            total += os.path.getsize(a) if os.path.isfile(a) else 0
        except OSError:
            pass
    return total


def _usable_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)
