"""Running jobs: each one is a ``forestreg`` CLI process in its own process group.

A job's arguments are the CLI's (``["register", "A.laz", "B.laz", "--out", "D"]``), checked by the
CLI's own argparse parser before they are queued (:func:`validate_args`). A worker thread of the
service starts ``forestreg ... --progress jsonl`` and reads its JSON-lines events on stderr:

    {"event": "progress", "step": "<id>", "fraction": 0..1, "message": "<text>"}
    {"event": "end", "exit_code": N, "message": "<one line>", "result": "<path or null>", "outputs": ["<path>", ...]}

``result`` and ``outputs`` are the files the command's use case reported it wrote (its outcome's
``result_file`` and ``outputs``): the job record shows exactly those (``result``, read; ``result_path``;
``outputs``), and nothing when the command reported none.

and, from a watching plot job (``plot --watch FOLDER``), one ``{"event": "scan", ...}`` per scan
taken in (:meth:`forestreg.app.watch.WatchEvent.to_dict`), kept as it is.

Other lines are kept as log events. Cancelling sends SIGINT to the job's process group and SIGKILL
after a grace period; the CLI writes its output folders as transactions, so a cancelled job leaves
them complete or absent.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from .store import FINAL, JobStore

log = logging.getLogger("forestreg.service")

#: commands that cannot run as jobs (interactive, or the service itself)
NOT_JOBS = frozenset({"gui", "serve"})

#: seconds between SIGINT and SIGKILL when a job is cancelled
CANCEL_GRACE_S = 10.0


class ArgumentError(ValueError):
    """Arguments the CLI would refuse; the message is the CLI's one line."""


class WorkingFolderNeeded(ValueError):
    """A job without a working folder names a relative path (the API's 422): the message names it."""


class OutputBusy(ValueError):
    """A job would write the output folder of a job that is queued or running (the API's 409)."""


# ----------------------------------------------------------------------------- arguments


def _raising(parser: argparse.ArgumentParser) -> None:
    """Make ``parser`` and its sub-parsers raise :class:`ArgumentError` instead of exiting."""

    def error(message: str, _p=parser):
        raise ArgumentError(f"{_p.prog}: error: {message}")

    def exit_(status: int = 0, message: Optional[str] = None, _p=parser):
        raise ArgumentError(f"{_p.prog}: error: {(message or 'help and version are not jobs').strip()}")

    parser.error = error  # type: ignore[method-assign]
    parser.exit = exit_  # type: ignore[method-assign]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _raising(sub)
        elif isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            pass


#: Builds the parser jobs are checked with: the CLI's own, handed over by the ``serve`` and
#: ``batch`` commands through :func:`use_parser` (the service never imports the CLI that starts it).
_parser_factory: Optional[Callable[[], argparse.ArgumentParser]] = None


def use_parser(factory: Callable[[], argparse.ArgumentParser]) -> None:
    """Check every job's arguments with the parser ``factory()`` builds (the CLI's)."""
    global _parser_factory
    _parser_factory = factory


def _parser() -> argparse.ArgumentParser:
    if _parser_factory is None:
        raise RuntimeError(
            "no command-line parser to check jobs with: call forestreg.service.jobs.use_parser(forestreg.cli.build_parser) "
            "first (the 'serve' and 'batch' commands do)"
        )
    parser = _parser_factory()
    _raising(parser)
    return parser


def validate_args(args: Sequence[str]) -> argparse.Namespace:
    """Parse ``args`` with the CLI's parser; :class:`ArgumentError` with its message if refused."""
    if not isinstance(args, (list, tuple)) or not all(isinstance(a, str) for a in args):
        raise ArgumentError("forestreg: error: args must be a list of strings")
    if not args:
        raise ArgumentError("forestreg: error: no command given")
    if any("\x00" in a for a in args):
        raise ArgumentError("forestreg: error: an argument holds a NUL byte")
    if args[0] in NOT_JOBS:
        raise ArgumentError(f"forestreg: error: '{args[0]}' cannot run as a job")
    try:
        return _parser().parse_args(list(args))
    except argparse.ArgumentTypeError as exc:  # pragma: no cover - argparse turns these into error()
        raise ArgumentError(f"forestreg: error: {exc}") from exc


# ----------------------------------------------------------------------------- paths in arguments

#: String arguments of the CLI that are not paths: scan and run names, spelled-out choices,
#: coordinates, addresses, sizes, options passed on. Any other string argument is taken as a path
#: (a new option counts as one until it is listed here: a job then needs a working folder).
_NOT_PATHS = frozenset(
    {
        "centre",
        "tilted",
        "pairs",
        "fixed",
        "name",
        "tilt",
        "host",
        "scheduler",
        "memory_limit",
        "preset",
        "gui_args",
        "extra",
        "progress",
        "command",
        "action",
    }
)
#: ... and those that are not paths in one command only ((command, action) -> argument names)
_NOT_PATHS_IN = {("project", "link"): frozenset({"moving", "reference"}), ("simulate", None): frozenset({"positions"})}
_GLOBAL_FLAGS = ("-v", "--verbose", "-q", "--quiet")


def _command_of(args: Sequence[str]) -> tuple[str, int]:
    """The command of ``args`` (after the global flags) and its index."""
    k = 0
    while k < len(args) and args[k].startswith("-"):
        k += 2 if args[k] == "--progress" else 1
    return (args[k], k) if k < len(args) else ("", k)


def _string_arguments(command: str, action: Optional[str]) -> list[str]:
    """The destinations of the string-valued arguments of ``command`` (and its ``action``)."""
    parser = _parser()
    for level in (command, action):
        if level is None:
            break
        sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None or level not in sub.choices:
            break
        parser = sub.choices[level]
    return [
        a.dest
        for a in parser._actions
        if a.nargs != 0
        and a.choices is None
        and a.type in (None, str)
        and not isinstance(a, argparse._SubParsersAction)
    ]


def _looks_like_path(token: str) -> bool:
    """A token of ``batch --extra`` taken as a path: it holds a separator or ends in a suffix."""
    import re

    if token.startswith("-"):
        return False
    try:
        float(token)
        return False
    except ValueError:
        pass
    return "/" in token or "\\" in token or re.search(r"\.[A-Za-z][A-Za-z0-9]{0,5}$", token) is not None


def path_arguments(args: Sequence[str], namespace: Optional[argparse.Namespace] = None) -> list[str]:
    """The paths a job's arguments name (inputs, outputs, parameter files, with the CLI's defaults
    of those not given), as written."""
    ns = namespace if namespace is not None else validate_args(args)
    command, _ = _command_of(list(args))
    action = getattr(ns, "action", None) if command == "project" else None
    skip = _NOT_PATHS | _NOT_PATHS_IN.get((command, action), frozenset())
    found: list[str] = []
    for dest in _string_arguments(command, action):
        if dest in skip:
            continue
        value = getattr(ns, dest, None)
        for v in value if isinstance(value, (list, tuple)) else [value]:
            if not isinstance(v, str) or not v:
                continue
            if dest == "also" and "=" in v and "/" not in v.split("=", 1)[0]:
                v = v.split("=", 1)[1]  # NAME=TREES
            found.append(v)
    extra = getattr(ns, "extra", None) if command == "batch" else None
    if isinstance(extra, str):
        import shlex

        try:
            found += [
                t.split("=", 1)[1] if t.startswith("--") and "=" in t else t
                for t in shlex.split(extra)
                if _looks_like_path(t.split("=", 1)[1] if t.startswith("--") and "=" in t else t)
            ]
        except ValueError:
            pass
    return found


def relative_paths(args: Sequence[str], namespace: Optional[argparse.Namespace] = None) -> list[str]:
    """The paths of ``args`` that are relative (they need the job's working folder)."""
    return [p for p in path_arguments(args, namespace) if not os.path.isabs(os.path.expanduser(p))]


def output_path(
    args: Sequence[str], cwd: Optional[str] = None, namespace: Optional[argparse.Namespace] = None
) -> Optional[str]:
    """The resolved output folder of a job (its ``--out``, symbolic links resolved), or None."""
    ns = namespace if namespace is not None else validate_args(args)
    out = getattr(ns, "out", None)
    if not isinstance(out, str) or not out:
        return None
    out = os.path.expanduser(out)
    if not os.path.isabs(out):
        if not cwd:
            return None
        out = os.path.join(cwd, out)
    return os.path.realpath(out)


def _overlaps(a: str, b: str) -> bool:
    """Whether the folders ``a`` and ``b`` are one, or one holds the other."""
    return a == b or a.startswith(b.rstrip(os.sep) + os.sep) or b.startswith(a.rstrip(os.sep) + os.sep)


def _package_env() -> dict[str, str]:
    """The environment of a job: this process's, with the ``forestreg`` package importable."""
    import forestreg

    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    # cancelling sends SIGINT: honoured even when this service was started with Ctrl-C ignored
    # (nohup, "&" in a script), which every job would inherit
    env["FORESTREG_INTERRUPTIBLE"] = "1"
    env.setdefault("MPLBACKEND", "Agg")
    package = Path(forestreg.__file__).parent  # not resolved: a symlinked package keeps its name
    if package.name == "forestreg":
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(package.parent), env.get("PYTHONPATH", "")) if p)
    return env


def job_command(args: Sequence[str]) -> list[str]:
    """The command line that runs ``args`` with JSON-lines progress on stderr (the CLI's global
    ``--progress jsonl``, unless the job chose its own ``--progress``)."""
    args = list(args)
    cli = [sys.executable, "-m", "forestreg.cli"]
    if any(a == "--progress" or a.startswith("--progress=") for a in args):
        return cli + args
    return cli + args + ["--progress", "jsonl"]


def read_result(path: Optional[str], cwd: Optional[str] = None) -> Any:
    """A result file as the API shows it: a JSON file's content, a CSV's rows, else the path."""
    if not path:
        return None
    p = Path(cwd or ".") / path
    try:
        if p.suffix == ".json" and p.stat().st_size < 20_000_000:
            return json.loads(p.read_text(encoding="utf-8"))
        if p.suffix == ".csv" and p.stat().st_size < 5_000_000:
            with p.open(newline="", encoding="utf-8") as fh:
                return {"path": str(p), "rows": list(csv.DictReader(fh))}
    except (OSError, ValueError):
        pass
    return {"path": str(p)}


def parse_event(line: str) -> Optional[dict]:
    """One JSON-lines event (``progress``, ``end``, or ``scan``: a scan a watching plot job took
    in) of the CLI, else None."""
    line = line.strip()
    if not line.startswith("{"):
        return None
    try:
        event = json.loads(line)
    except ValueError:
        return None
    if not isinstance(event, dict) or event.get("event") not in ("progress", "end", "scan"):
        return None
    return event


# ----------------------------------------------------------------------------- the manager


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True


def _is_job_process(pid: int) -> bool:
    try:
        return b"forestreg" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return os.name != "posix" or not Path("/proc").is_dir()


def _signal_group(pid: int, sig: int) -> None:
    try:
        if os.name == "posix":
            os.killpg(pid, sig)  # the job leads its own session: pgid == pid
        else:  # pragma: no cover
            os.kill(pid, signal.CTRL_BREAK_EVENT if sig == signal.SIGINT else signal.SIGTERM)
    except (ProcessLookupError, PermissionError):
        pass


class JobManager:
    """Queues jobs in the store and runs up to ``workers`` of them at once."""

    def __init__(
        self, store: JobStore, workers: int = 1, grace_s: float = CANCEL_GRACE_S, work_dir: Optional[Path] = None
    ) -> None:
        self.store = store
        self.workers = max(1, int(workers))
        self.grace_s = grace_s
        #: where a job sent without a working folder runs (``STATE/work/<job id>``, its own folder)
        self.work_dir = Path(work_dir) if work_dir is not None else Path(store.path).parent / "work"
        self._procs: dict[str, subprocess.Popen] = {}
        self._lock = threading.Lock()
        self._submit_lock = threading.Lock()  # the check of the output folders and the queueing: one job at a time
        self._outputs: dict[str, Optional[str]] = {}  # job id -> its resolved output folder (a cache)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.last_activity = time.monotonic()

    # ----------------------------------------------------------------------------- life cycle

    def start(self) -> None:
        orphans = [
            job["pid"]
            for job in self.store.recover()
            if job.get("pid") and _alive(job["pid"]) and _is_job_process(job["pid"])
        ]
        if orphans:  # jobs of a service that was killed still run: stop them as a cancel would
            threading.Thread(target=self._stop_orphans, args=(orphans,), daemon=True).start()
        for k in range(self.workers):
            t = threading.Thread(target=self._loop, name=f"forestreg-job-{k}", daemon=True)
            t.start()
            self._threads.append(t)

    def _stop_orphans(self, pids: list[int]) -> None:
        for pid in pids:
            _signal_group(pid, signal.SIGINT)  # the CLI removes its temporary output folder
        deadline = time.monotonic() + self.grace_s
        while time.monotonic() < deadline and any(_alive(p) for p in pids):
            time.sleep(0.2)
        for pid in pids:
            if _alive(pid):
                _signal_group(pid, signal.SIGKILL)

    def shutdown(self) -> None:
        """Stop taking jobs; stop the running ones (they are marked interrupted)."""
        self._stop.set()
        self._wake.set()
        with self._lock:
            procs = dict(self._procs)
        for proc in procs.values():
            _signal_group(proc.pid, signal.SIGINT)
        deadline = time.monotonic() + self.grace_s
        for proc in procs.values():
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                _signal_group(proc.pid, signal.SIGKILL)
        for t in self._threads:
            t.join(timeout=5)

    def kill_all(self) -> None:
        """SIGKILL every running job's process group (the last resort of a service that must end)."""
        with self._lock:
            procs = list(self._procs.values())
        for proc in procs:
            _signal_group(proc.pid, signal.SIGKILL)

    def busy(self) -> bool:
        return self.store.count("running") > 0 or self.store.count("queued") > 0

    # ----------------------------------------------------------------------------- requests

    def submit(self, args: Sequence[str], cwd: Optional[str] = None) -> str:
        """Queue a job; returns its id. Refused: arguments the CLI refuses (:class:`ArgumentError`);
        without ``cwd``, a relative path in them (:class:`WorkingFolderNeeded`; the job would run
        in a private folder of the service); an output folder that is, holds or lies in the output
        folder of a job queued or running (:class:`OutputBusy`)."""
        ns = validate_args(args)
        if cwd is not None and "\x00" in cwd:
            raise ArgumentError("forestreg: error: the working directory holds a NUL byte")
        if cwd is not None and not os.path.isabs(cwd):
            raise WorkingFolderNeeded(f"the working folder {cwd!r} is not an absolute path")
        if cwd is not None and not Path(cwd).is_dir():
            raise ArgumentError(f"forestreg: error: working directory {cwd} does not exist")
        if cwd is None:
            relative = relative_paths(args, ns)
            if relative:
                where = ", ".join(repr(p) for p in relative[:3]) + (", ..." if len(relative) > 3 else "")
                raise WorkingFolderNeeded(
                    f"required: {where} {'is a relative path' if len(relative) == 1 else 'are relative paths'}: "
                    "send the client's working folder as cwd (an absolute path), or give every path absolute"
                )
        out = output_path(args, cwd, ns)
        with self._submit_lock:
            if out is not None:
                for job, status in self._active_jobs():
                    theirs = self._output_of(job)
                    if theirs is not None and _overlaps(out, theirs):
                        relation = "is" if out == theirs else ("is inside" if out.startswith(theirs) else "holds")
                        raise OutputBusy(
                            f"--out {out} {relation} the output folder of job {job['id']} ({status}"
                            f"{', ' + theirs if out != theirs else ''}): wait for it to end, cancel it, or give "
                            "another output folder"
                        )
            job_id = self.store.add(list(args), cwd)
            self._outputs[job_id] = out
        self.last_activity = time.monotonic()
        self._wake.set()
        return job_id

    def _active_jobs(self) -> list[tuple[dict, str]]:
        """The jobs queued or running: ({id, args, cwd}, status)."""
        store = self.store
        with store._lock:  # one query of the store's own connection (its lock serialises it)
            rows = store._db.execute(
                "SELECT id, args, cwd, status FROM jobs WHERE status IN ('queued', 'running')"
            ).fetchall()
        return [({"id": job["id"], "args": json.loads(job["args"]), "cwd": job["cwd"]}, job["status"]) for job in rows]

    def _output_of(self, job: dict) -> Optional[str]:
        """The resolved output folder of a stored job (parsed once; None when it has none)."""
        if job["id"] not in self._outputs:
            try:
                self._outputs[job["id"]] = output_path(job["args"], job["cwd"])
            except ArgumentError:
                self._outputs[job["id"]] = None
        return self._outputs[job["id"]]

    def cancel(self, job_id: str) -> Optional[dict]:
        job = self.store.get(job_id)
        if job is None or job["status"] in FINAL:
            return job
        self.store.update(job_id, cancel_requested=1)
        if job["status"] == "queued":
            self.store.update(job_id, status="cancelled", message="cancelled before it started", finished=time.time())
            self._outputs.pop(job_id, None)
            self.store.add_event(job_id, {"event": "status", "status": "cancelled"})
            return self.store.get(job_id)
        with self._lock:
            proc = self._procs.get(job_id)
        if proc is not None:
            self.store.update(job_id, message="cancelling")
            _signal_group(proc.pid, signal.SIGINT)

            def kill_later() -> None:
                try:
                    proc.wait(timeout=self.grace_s)
                except subprocess.TimeoutExpired:
                    _signal_group(proc.pid, signal.SIGKILL)

            threading.Thread(target=kill_later, daemon=True).start()
        return self.store.get(job_id)

    # ----------------------------------------------------------------------------- running

    def _loop(self) -> None:
        while not self._stop.is_set():
            job = self.store.claim_next()
            if job is None:
                self._wake.wait(0.5)
                self._wake.clear()
                continue
            try:
                self._run(job)
            except Exception as exc:  # never lose the worker thread
                log.exception("job %s", job["id"])
                self.store.update(
                    job["id"], status="error", message=f"the service could not run the job: {exc}", finished=time.time()
                )
                self.store.add_event(job["id"], {"event": "status", "status": "error"})
            self.last_activity = time.monotonic()

    def _run(self, job: dict) -> None:
        try:
            self._run_in(job)
        finally:
            self._outputs.pop(job["id"], None)

    def _private_folder(self, job_id: str) -> Path:
        """``STATE/work/<job id>``: the working folder of a job sent without one (every path in it
        is absolute); readable by the user only."""
        from ..engine.core.names import safe_name

        folder = self.work_dir / safe_name(job_id, "job id")
        self.work_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        folder.mkdir(exist_ok=True, mode=0o700)
        return folder

    def _run_in(self, job: dict) -> None:
        job_id, args, cwd = job["id"], job["args"], job["cwd"]
        cmd = job_command(args)
        private = None
        try:
            if not cwd:
                private = self._private_folder(job_id)
            proc = subprocess.Popen(
                cmd,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                cwd=str(private) if private is not None else cwd,
                env=_package_env(),
                start_new_session=True,
            )
        except OSError as exc:
            self.store.update(job_id, status="error", message=f"cannot start the job: {exc}", finished=time.time())
            self.store.add_event(job_id, {"event": "status", "status": "error"})
            if private is not None:
                self._tidy(job_id, private)
            return
        if private is not None:
            cwd = str(private)
        with self._lock:
            self._procs[job_id] = proc
        self.store.update(job_id, pid=proc.pid, message="running")
        if self.store.raw(job_id)["cancel_requested"]:  # cancelled between claim and start
            _signal_group(proc.pid, signal.SIGINT)
        lines: list[str] = []  # non-event lines, for the message of a failure
        end: dict = {}

        def read_stdout() -> None:
            for raw in iter(proc.stdout.readline, b""):
                text = raw.decode("utf-8", "replace").rstrip()
                if text:
                    lines.append(text)
                    self.store.add_event(job_id, {"event": "log", "stream": "stdout", "message": text})

        reader = threading.Thread(target=read_stdout, daemon=True)
        reader.start()
        last = {"t": 0.0, "fraction": -1.0, "step": None, "message": None}
        for raw in iter(proc.stderr.readline, b""):
            text = raw.decode("utf-8", "replace").rstrip()
            if not text:
                continue
            event = parse_event(text)
            if event is None:
                lines.append(text)
                self.store.add_event(job_id, {"event": "log", "stream": "stderr", "message": text})
                continue
            if event["event"] == "end":
                end = event
                continue
            if event["event"] == "scan":  # a watching plot job: each scan's outcome, streamed as it is
                self.store.update(job_id, message=str(event.get("message") or ""))
                self.store.add_event(job_id, event)
                continue
            fraction = min(max(float(event.get("fraction") or 0.0), 0.0), 1.0)
            step, message = str(event.get("step") or ""), str(event.get("message") or "")
            now = time.monotonic()
            # keep every change of step or message; thin out a fast stream of fractions
            if (
                step == last["step"]
                and message == last["message"]
                and abs(fraction - last["fraction"]) < 0.01
                and now - last["t"] < 0.5
            ):
                continue
            last.update(t=now, fraction=fraction, step=step, message=message)
            self.store.update(job_id, progress=fraction, step=step, message=message)
            self.store.add_event(job_id, {"event": "progress", "step": step, "fraction": fraction, "message": message})
        proc.wait()
        reader.join(timeout=10)
        for stream in (proc.stdout, proc.stderr):
            stream.close()
        with self._lock:
            self._procs.pop(job_id, None)
        code = proc.returncode
        if end.get("exit_code") is not None and code == 0:
            code = int(end["exit_code"])
        cancelled = bool(self.store.raw(job_id)["cancel_requested"])
        if cancelled:
            status, message = "cancelled", "cancelled: the run was stopped"
        elif self._stop.is_set() and code != 0:
            status, message = "interrupted", "interrupted: the service stopped while the job ran (resubmit it)"
        elif code in (0, 1):
            status = "done"
            message = str(end.get("message") or (lines[-1] if lines else "done"))
        else:
            status = "error"
            message = str(end.get("message") or _error_line(lines) or f"the command stopped with exit status {code}")
        result_path = None if cancelled else end.get("result")
        if result_path:
            result_path = str((Path(cwd or ".") / result_path).resolve())
        outputs = (
            []
            if cancelled
            else [str((Path(cwd or ".") / p).resolve()) for p in end.get("outputs") or () if isinstance(p, str)]
        )
        fields: dict[str, Any] = dict(
            status=status, exit_code=code, message=message, finished=time.time(), outputs=json.dumps(outputs)
        )
        if status == "done":
            fields["progress"] = 1.0
        if result_path:
            fields["result"] = json.dumps(read_result(result_path, cwd))
            fields["result_path"] = str(result_path)
        if private is not None:
            self._tidy(job_id, private)
        self.store.update(job_id, **fields)
        self.store.add_event(
            job_id,
            {
                "event": "end",
                "status": status,
                "exit_code": code,
                "message": message,
                "result": result_path,
                "outputs": outputs,
            },
        )

    def _tidy(self, job_id: str, private: Path) -> None:
        """Remove a job's private folder when the job left nothing in it (else keep it, and say so)."""
        try:
            private.rmdir()
        except FileNotFoundError:
            pass
        except OSError:
            self.store.add_event(
                job_id,
                {"event": "log", "stream": "service", "message": f"the job left files in its working folder {private}"},
            )


def _error_line(lines: list[str]) -> str:
    for line in reversed(lines):
        if "error:" in line:
            return line.split("error:", 1)[1].strip()
    return lines[-1] if lines else ""
