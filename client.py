"""A small client of the forestreg job service (``forestreg serve``), for scripts, notebooks and
the plugin hosts. Standard library only, so it imports in QGIS's and CloudCompare's Python.

    from forestreg.client import connect

    service = connect()                      # the running service (started if it is not)
    job = service.submit(["register", "A.laz", "B.laz", "--out", "pair"])
    final = service.wait(job, progress=lambda f, msg: print(f"{100 * f:3.0f}% {msg}"))
    print(final["status"], final["exit_code"], final["result"]["matrix"])

The service's address and token are read from its state folder (``server.json`` and ``token``;
default: ``$FORESTREG_SERVICE_DIR`` or the user's data directory), or given explicitly:
``Client("http://127.0.0.1:8754", token="...")``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any, Callable, Iterator, Optional, Sequence, Union

STATE_ENV = "FORESTREG_SERVICE_DIR"
FINAL = ("done", "cancelled", "error", "interrupted")

ProgressCallback = Callable[[float, str], None]


def default_state_dir() -> Path:
    """``$FORESTREG_SERVICE_DIR``, else ``<user data dir>/forestreg/service`` (Linux
    ``~/.local/share``, macOS ``~/Library/Application Support``, Windows ``%LOCALAPPDATA%``)."""
    env = os.environ.get(STATE_ENV, "").strip()
    if env:
        return Path(env).expanduser()
    if sys.platform.startswith("win"):
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Application Support"
    else:
        base = Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")
    return base / "forestreg" / "service"


class ServiceError(RuntimeError):
    """The service answered with an error (``status``: the HTTP status; ``detail``: its message),
    or could not be reached (``status`` None)."""

    def __init__(self, message: str, status: Optional[int] = None, detail: str = "") -> None:
        super().__init__(message)
        self.status = status
        self.detail = detail or message


class Client:
    """The service's HTTP/JSON API as methods (every call bounded by ``timeout`` seconds)."""

    def __init__(
        self,
        url: Optional[str] = None,
        token: Optional[str] = None,
        state_dir: Optional[Union[str, Path]] = None,
        timeout: float = 30.0,
    ) -> None:
        state = Path(state_dir) if state_dir else default_state_dir()
        if url is None:
            info = read_server_info(state)
            if info is None:
                raise ServiceError(f"no forestreg service runs with state folder {state} (start one: forestreg serve)")
            url = info["url"]
        if token is None:
            try:
                token = (state / "token").read_text(encoding="utf-8").strip()
            except OSError:
                token = ""
        self.url = url.rstrip("/")
        self.token = token
        self.timeout = timeout

    # ----------------------------------------------------------------------------- plumbing

    def _request(self, method: str, path: str, body: Any = None, timeout: Optional[float] = None, auth: bool = True):
        data = None if body is None else json.dumps(body).encode("utf-8")
        headers = {"Accept": "application/json"}
        if data is not None:
            headers["Content-Type"] = "application/json"
        if auth and self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        req = urllib.request.Request(self.url + path, data=data, headers=headers, method=method)
        try:
            return urllib.request.urlopen(req, timeout=timeout or self.timeout)
        except urllib.error.HTTPError as exc:
            try:
                detail = json.loads(exc.read().decode("utf-8")).get("detail", "")
            except Exception:
                detail = exc.reason
            raise ServiceError(f"{method} {path}: {exc.code} {detail}", exc.code, str(detail)) from None
        except (urllib.error.URLError, OSError) as exc:
            raise ServiceError(
                f"cannot reach the forestreg service at {self.url}: {getattr(exc, 'reason', exc)}"
            ) from None

    def _json(self, method: str, path: str, body: Any = None, auth: bool = True) -> Any:
        with self._request(method, path, body, auth=auth) as resp:
            return json.loads(resp.read().decode("utf-8"))

    # ----------------------------------------------------------------------------- the API

    def health(self) -> dict:
        return self._json("GET", "/v1/health", auth=False)

    def submit(self, args: Sequence[str], cwd: Optional[Union[str, Path]] = None) -> str:
        """Queue a command (the CLI's arguments); relative paths are taken from ``cwd`` (default:
        this process's working directory). Bad arguments: :class:`ServiceError` with status 400
        and the CLI's message."""
        body = {"args": [str(a) for a in args], "cwd": str(Path(cwd or os.getcwd()).resolve())}
        return self._json("POST", "/v1/jobs", body)["id"]

    def job(self, job_id: str) -> dict:
        return self._json("GET", f"/v1/jobs/{urllib.parse.quote(job_id)}")

    def jobs(self) -> list[dict]:
        return self._json("GET", "/v1/jobs")["jobs"]

    def cancel(self, job_id: str) -> dict:
        return self._json("DELETE", f"/v1/jobs/{urllib.parse.quote(job_id)}")

    def resubmit(self, job_id: str) -> str:
        return self._json("POST", f"/v1/jobs/{urllib.parse.quote(job_id)}/resubmit")["id"]

    def events(self, job_id: str, after: int = 0, keepalive: bool = False) -> Iterator[Optional[dict]]:
        """The job's events (server-sent) from event ``after`` on, until its ``end`` event.
        With ``keepalive`` a None comes at least about once a second while nothing happens."""
        path = f"/v1/jobs/{urllib.parse.quote(job_id)}/events?after={int(after)}"
        with self._request("GET", path, timeout=max(self.timeout, 10.0)) as resp:
            data: list[str] = []
            event_id = None
            while True:
                raw = resp.readline()
                if not raw:
                    return
                line = raw.decode("utf-8").rstrip("\r\n")
                if line.startswith(":"):
                    if keepalive:
                        yield None
                    continue
                if line.startswith("data:"):
                    data.append(line[5:].strip())
                elif line.startswith("id:"):
                    event_id = line[3:].strip()
                elif line == "" and data:
                    event = json.loads("\n".join(data))
                    if event_id is not None:
                        event["_id"] = int(event_id)
                    data, event_id = [], None
                    yield event
                    if event.get("event") == "end":
                        return

    def wait(
        self,
        job_id: str,
        progress: Optional[ProgressCallback] = None,
        log: Optional[Callable[[str], None]] = None,
        cancelled: Optional[Callable[[], bool]] = None,
        timeout: Optional[float] = None,
    ) -> dict:
        """Follow the job's events until it ends and return its final state.

        ``progress(fraction, message)`` gets each progress event, ``log(line)`` each output line;
        ``cancelled()`` is asked about once a second and a true answer cancels the job (its
        final state, ``cancelled``, is returned). ``timeout`` (s) raises :class:`TimeoutError`.
        """
        t0 = time.monotonic()
        after = 0
        failures = 0
        cancel_sent = False
        while True:
            try:
                for event in self.events(job_id, after, keepalive=True):
                    if event is not None:
                        after = event.get("_id", after)
                        kind = event.get("event")
                        if kind == "progress" and progress is not None:
                            progress(
                                float(event.get("fraction") or 0.0),
                                str(event.get("message") or event.get("step") or ""),
                            )
                        elif kind == "log" and log is not None:
                            log(str(event.get("message", "")))
                    if cancelled is not None and not cancel_sent and cancelled():
                        self.cancel(job_id)
                        cancel_sent = True
                    if timeout is not None and time.monotonic() - t0 > timeout:
                        raise TimeoutError(f"job {job_id} did not end within {timeout:.0f} s")
                failures = 0
            except ServiceError:
                failures += 1
                if failures > 5:
                    raise
                time.sleep(0.5)
            job = self.job(job_id)
            if job["status"] in FINAL:
                return job
            if timeout is not None and time.monotonic() - t0 > timeout:
                raise TimeoutError(f"job {job_id} did not end within {timeout:.0f} s")

    def run(self, args: Sequence[str], cwd: Optional[Union[str, Path]] = None, **wait_options: Any) -> dict:
        """Submit and wait: the job's final state."""
        return self.wait(self.submit(args, cwd), **wait_options)


# ----------------------------------------------------------------------------- finding / starting


def read_server_info(state_dir: Union[str, Path]) -> Optional[dict]:
    """``server.json`` of the service using ``state_dir`` (url, port, pid), if it is there."""
    try:
        return json.loads((Path(state_dir) / "server.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _reachable(state: Path) -> Optional[Client]:
    info = read_server_info(state)
    if info is None:
        return None
    try:
        client = Client(info["url"], state_dir=state, timeout=5.0)
        if client.health().get("service") == "forestreg":
            client.timeout = 30.0
            return client
    except (ServiceError, ValueError, KeyError):
        pass
    return None


def start_service(
    state_dir: Optional[Union[str, Path]] = None,
    command: Optional[Sequence[str]] = None,
    env: Optional[dict] = None,
    idle_exit_s: Optional[float] = 900.0,
    workers: int = 1,
    timeout: float = 60.0,
) -> Client:
    """Start ``forestreg serve`` in the background on a free loopback port and wait until it answers.
    ``command``: how to run the CLI (default ``python -m forestreg.cli``)."""
    state = Path(state_dir) if state_dir else default_state_dir()
    state.mkdir(parents=True, exist_ok=True)
    cmd = [str(c) for c in (command or [sys.executable, "-m", "forestreg.cli"])]
    cmd += ["serve", "--port", "0", "--state", str(state), "--workers", str(workers)]
    if idle_exit_s:
        cmd += ["--idle-exit", str(idle_exit_s)]
    kwargs: dict = {}
    if os.name == "nt":  # pragma: no cover
        kwargs["creationflags"] = getattr(subprocess, "CREATE_NO_WINDOW", 0) | getattr(
            subprocess, "CREATE_NEW_PROCESS_GROUP", 0
        )
    else:
        kwargs["start_new_session"] = True  # outlives the host that started it
    with (state / "service.log").open("ab") as logfile:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=logfile, stderr=logfile, env=env, **kwargs)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        info = read_server_info(state)
        if info is not None and info.get("pid") == proc.pid:
            client = _reachable(state)
            if client is not None:
                return client
        code = proc.poll()
        if code is not None:
            client = _reachable(state)  # another start won the race: use that one
            if client is not None:
                return client
            tail = (state / "service.log").read_text(encoding="utf-8", errors="replace").strip().splitlines()[-1:]
            raise ServiceError(
                f"the forestreg service did not start (exit status {code}): {tail[0] if tail else 'no message'}"
            )
        time.sleep(0.2)
    raise ServiceError(f"the forestreg service did not answer within {timeout:.0f} s (see {state / 'service.log'})")


def connect(state_dir: Optional[Union[str, Path]] = None, start: bool = True, **start_options: Any) -> Client:
    """A client of the service using ``state_dir``; starts one (see :func:`start_service`) when
    none answers and ``start`` is true."""
    state = Path(state_dir) if state_dir else default_state_dir()
    client = _reachable(state)
    if client is not None:
        return client
    if not start:
        raise ServiceError(f"no forestreg service answers for state folder {state}")
    return start_service(state, **start_options)


__all__ = ["Client", "ServiceError", "connect", "start_service", "default_state_dir", "read_server_info"]
