"""The HTTP/JSON API of ``forestreg serve`` (FastAPI on uvicorn).

Every route but ``GET /v1/health`` needs ``Authorization: Bearer <token>`` (the token lives in
``STATE/token``, readable by the user only). The OpenAPI description is ``/v1/openapi.json``.

    GET    /v1/health                 {"status": "ok", "version": ...}
    POST   /v1/jobs                   {"args": [...], "cwd": "/abs/folder"} -> 201 {"id": ...}; 400 arguments the
                                      CLI refuses; 409 its --out is (or holds, or lies in) the output folder
                                      of a job queued or running; 413 a body over 1 MiB; 422 a cwd that is
                                      not absolute, no cwd while args hold a relative path, over 2,000
                                      arguments, an argument over 4,096 characters, or a NUL byte
    GET    /v1/jobs                   {"jobs": [...]} (newest first)
    GET    /v1/jobs/{id}              the job: status, progress, step, message, exit_code, result
    GET    /v1/jobs/{id}/events       server-sent events: status, progress, log, end
    DELETE /v1/jobs/{id}              cancel (SIGINT to the job's process group, SIGKILL after a grace)
                                      -> 202; 409 when the job has already ended (the answer names its status)
    POST   /v1/jobs/{id}/resubmit     the same arguments as a new job -> 201 {"id": ...}

A job runs in the working folder ``cwd`` the client sends (an absolute path; the Python client sends
its own working folder): relative paths in ``args`` are taken from there, never from the service's
own working folder. A job whose paths are all absolute may come without ``cwd``: it then runs in a
private folder of its own (``STATE/work/<id>``, removed after it when empty). SIGTERM or Ctrl-C stops the service: running jobs are stopped (marked
``interrupted``) and the state folder is unlocked, also when a request is still being answered.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import os
import secrets
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Optional

from fastapi import Depends, FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, Field, field_validator

from ..client import default_state_dir, read_server_info
from .jobs import ArgumentError, JobManager, OutputBusy, WorkingFolderNeeded
from .store import FINAL, JobStore

log = logging.getLogger("forestreg.service")

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8754

#: the largest request body read (bytes); a larger one is refused with 413 before it is parsed
MAX_BODY_BYTES = 1 << 20
#: the most arguments of one job, and the longest argument (characters)
MAX_ARGS = 2000
MAX_ARG_CHARS = 4096
#: seconds a stopping service waits for open requests before it closes them
SHUTDOWN_GRACE_S = 3.0


def ensure_token(state_dir: Path) -> str:
    """``STATE/token``: created on first start (mode 0600), read afterwards."""
    state_dir.mkdir(parents=True, exist_ok=True)
    with contextlib.suppress(OSError):
        os.chmod(state_dir, 0o700)
    path = state_dir / "token"
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        with contextlib.suppress(OSError):
            os.chmod(path, 0o600)  # readable by the user only, also if someone loosened it
        token = path.read_text(encoding="utf-8").strip()
        if token:
            return token
        path.unlink()
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    token = secrets.token_urlsafe(32)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(token + "\n")
    return token


class JobRequest(BaseModel):
    args: list[str] = Field(
        ..., description=f"the CLI's arguments, e.g. ['register', 'A.laz', 'B.laz', '--out', 'D'] (at most {MAX_ARGS})"
    )
    cwd: Optional[str] = Field(
        None,
        description="the client's working folder, an absolute path: the job runs there and relative paths in "
        "args are taken from it; may be left out when every path in args is absolute",
    )

    @field_validator("args")
    @classmethod
    def _args(cls, args: list[str]) -> list[str]:
        if len(args) > MAX_ARGS:
            raise ValueError(f"{len(args)} arguments: at most {MAX_ARGS}")
        for a in args:
            if len(a) > MAX_ARG_CHARS:
                raise ValueError(f"an argument of {len(a)} characters: at most {MAX_ARG_CHARS}")
            if "\x00" in a:
                raise ValueError("an argument holds a NUL byte")
        return args

    @field_validator("cwd")
    @classmethod
    def _cwd(cls, cwd: Optional[str]) -> Optional[str]:
        if cwd is None:
            return None
        if "\x00" in cwd:
            raise ValueError("the working folder holds a NUL byte")
        if not os.path.isabs(cwd):
            raise ValueError(
                "must be the client's working folder as an absolute path (relative paths in args are taken from it)"
            )
        return cwd


class JobId(BaseModel):
    id: str


class BodyLimit:
    """ASGI middleware: a request body over ``limit`` bytes is answered 413 before anything parses it
    (the declared Content-Length, or the bytes received when the client does not declare it)."""

    def __init__(self, app, limit: int = MAX_BODY_BYTES) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        for name, value in scope.get("headers", ()):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = self.limit + 1
                if declared > self.limit:
                    return await self._refuse(send, receive, more=True)
        messages, size = [], 0
        if scope.get("method") in ("POST", "PUT", "PATCH"):
            while True:  # read the body (bounded), then hand it on
                message = await receive()
                messages.append(message)
                if message["type"] != "http.request":
                    break
                size += len(message.get("body", b""))
                if size > self.limit:
                    return await self._refuse(send, receive, more=message.get("more_body", False))
                if not message.get("more_body", False):
                    break
        pending = list(messages)

        async def replay():
            if pending:
                return pending.pop(0)
            return await receive()

        return await self.app(scope, replay, send)

    async def _refuse(self, send, receive, more: bool) -> None:
        drained = 0  # read (and drop) a moderate rest, so the client is not cut off while it sends
        while more and drained < 64 * self.limit:
            message = await receive()
            if message["type"] != "http.request":
                break
            drained += len(message.get("body", b""))
            more = message.get("more_body", False)
        body = json.dumps({"detail": f"request body over {self.limit} bytes"}).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})


def create_app(
    state_dir: Path, workers: int = 1, grace_s: Optional[float] = None, on_shutdown: Optional[Callable[[], None]] = None
) -> FastAPI:
    """The application with its job store and worker threads (started on application start-up)."""
    from .. import __version__

    state_dir = Path(state_dir)
    token = ensure_token(state_dir)
    store = JobStore(state_dir / "jobs.sqlite")
    manager = JobManager(store, workers=workers, **({} if grace_s is None else {"grace_s": grace_s}))

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        manager.start()
        try:
            yield
        finally:
            if on_shutdown is not None:
                on_shutdown()
            await asyncio.to_thread(manager.shutdown)
            store.close()

    app = FastAPI(
        title="forestreg job service",
        version=__version__,
        lifespan=lifespan,
        openapi_url=None,
        docs_url=None,
        redoc_url=None,
        description="Queue forestreg commands (the CLI's arguments), watch their progress, cancel them.",
    )
    app.state.manager = manager
    app.state.store = store
    app.state.stopping = threading.Event()  # set when the service is asked to stop: event streams end
    app.add_middleware(BodyLimit, limit=MAX_BODY_BYTES)
    bearer = HTTPBearer(auto_error=False)

    @app.middleware("http")
    async def touch(request: Request, call_next):
        manager.last_activity = time.monotonic()  # for --idle-exit
        return await call_next(request)

    def authorised(credentials: Optional[HTTPAuthorizationCredentials] = Depends(bearer)) -> None:
        if (
            credentials is None
            or credentials.scheme.lower() != "bearer"
            or not secrets.compare_digest(credentials.credentials, token)
        ):
            raise HTTPException(
                401,
                "missing or wrong token (Authorization: Bearer <STATE/token>)",
                headers={"WWW-Authenticate": "Bearer"},
            )

    def job_or_404(job_id: str) -> dict:
        job = store.get(job_id)
        if job is None:
            raise HTTPException(404, f"no job {job_id}")
        return job

    @app.get("/v1/openapi.json", dependencies=[Depends(authorised)], include_in_schema=False)
    def openapi() -> dict:
        return app.openapi()

    @app.get("/v1/health")
    def health() -> dict:
        return {"status": "ok", "service": "forestreg", "version": __version__, "workers": manager.workers}

    @app.post("/v1/jobs", status_code=201, response_model=JobId, dependencies=[Depends(authorised)])
    def submit(request: JobRequest) -> dict:
        return {"id": queue(request.args, request.cwd)}

    def queue(args: list[str], cwd: Optional[str]) -> str:
        try:
            return manager.submit(args, cwd)
        except ArgumentError as exc:
            raise HTTPException(400, str(exc)) from None
        except WorkingFolderNeeded as exc:
            raise HTTPException(422, f"cwd: {exc}") from None
        except OutputBusy as exc:
            raise HTTPException(409, str(exc)) from None

    @app.get("/v1/jobs", dependencies=[Depends(authorised)])
    def jobs(limit: int = 1000) -> dict:
        return {"jobs": store.list(limit)}

    @app.get("/v1/jobs/{job_id}", dependencies=[Depends(authorised)])
    def job(job_id: str) -> dict:
        return job_or_404(job_id)

    @app.delete("/v1/jobs/{job_id}", status_code=202, dependencies=[Depends(authorised)])
    def cancel(job_id: str) -> dict:
        job = job_or_404(job_id)
        if job["status"] in FINAL:
            raise HTTPException(409, f"job {job_id} has already ended: {job['status']}")
        return manager.cancel(job_id)

    @app.post("/v1/jobs/{job_id}/resubmit", status_code=201, response_model=JobId, dependencies=[Depends(authorised)])
    def resubmit(job_id: str) -> dict:
        old = job_or_404(job_id)
        if old["cwd"] and not os.path.isabs(old["cwd"]):
            raise HTTPException(
                422, f"job {job_id} has no absolute working folder: submit its arguments again with cwd"
            )
        return {"id": queue(old["args"], old["cwd"] or None)}

    @app.get("/v1/jobs/{job_id}/events", dependencies=[Depends(authorised)])
    async def events(job_id: str, request: Request) -> StreamingResponse:
        job_or_404(job_id)
        try:
            after = int(request.headers.get("last-event-id") or request.query_params.get("after") or 0)
        except ValueError:
            after = 0

        async def stream():
            nonlocal after
            last_sent = time.monotonic()
            while True:
                for n, event in store.events(job_id, after):
                    after = n
                    yield f"id: {n}\nevent: {event.get('event', 'message')}\ndata: {json.dumps(event)}\n\n"
                    last_sent = time.monotonic()
                    if event.get("event") == "end":
                        return
                job = store.get(job_id)
                if job is None or (job["status"] in FINAL and not store.events(job_id, after)):
                    if job is not None and job["status"] in ("cancelled", "interrupted"):
                        yield f"event: end\ndata: {json.dumps({'event': 'end', 'status': job['status'], 'exit_code': job['exit_code'], 'message': job['message'], 'result': None, 'outputs': []})}\n\n"
                    return
                if await request.is_disconnected():
                    return
                if app.state.stopping.is_set():
                    yield f"event: status\ndata: {json.dumps({'event': 'status', 'status': 'service stopping'})}\n\n"
                    return
                if time.monotonic() - last_sent > 1.0:  # a comment line keeps readers' loops turning
                    yield ": keep-alive\n\n"
                    last_sent = time.monotonic()
                await asyncio.sleep(0.2)

        return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        """422 with one line naming the first wrong field (not pydantic's list of dicts)."""
        errors = exc.errors()
        first = errors[0] if errors else {}
        where = ".".join(str(p) for p in first.get("loc", ()) if p != "body") or "body"
        what = str(first.get("msg", "invalid request")).removeprefix("Value error, ")
        if where == "cwd" and first.get("type") != "value_error":
            what = "must be the client's working folder as an absolute path (a string; relative paths in args are taken from it)"
        elif first.get("type") == "missing":
            what = "missing"
        return JSONResponse({"detail": f"{where}: {what}"}, status_code=422)

    @app.exception_handler(ArgumentError)
    async def bad_arguments(request: Request, exc: ArgumentError) -> JSONResponse:  # pragma: no cover - defensive
        return JSONResponse({"detail": str(exc)}, status_code=400)

    return app


# ----------------------------------------------------------------------------- running


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class ServiceRunning(RuntimeError):
    """Another service already runs with the same state directory."""


def _lock(state_dir: Path):
    """An exclusive lock on ``STATE/service.lock`` (released by the OS when the process dies)."""
    fh = open(state_dir / "service.lock", "a+")
    try:
        import fcntl

        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except ImportError:  # pragma: no cover - Windows: no lock
        pass
    except OSError:
        fh.close()
        info = read_server_info(state_dir) or {}
        raise ServiceRunning(
            f"a forestreg service already runs with {state_dir} at {info.get('url', '?')} (pid {info.get('pid', '?')})"
        ) from None
    return fh


def serve(
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    state_dir: Optional[Path] = None,
    workers: int = 1,
    idle_exit_s: Optional[float] = None,
    grace_s: Optional[float] = None,
) -> int:
    """Run the service until interrupted (or idle for ``idle_exit_s``). Port 0 picks a free port;
    the address is written to ``STATE/server.json`` once the service listens."""
    import uvicorn

    from ..engine.core.atomic import write_text_atomic

    state_dir = Path(state_dir) if state_dir else default_state_dir()
    state_dir.mkdir(parents=True, exist_ok=True)
    lock = _lock(state_dir)
    if not _is_loopback(host):
        print(
            f"forestreg serve: warning: listening on {host}, not only on this machine: anyone who can reach it "
            "and has the token can run commands as this user",
            file=sys.stderr,
        )
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        lock.close()
        raise OSError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    sock.listen(128)
    port = sock.getsockname()[1]

    def forget_address() -> None:  # before uvicorn re-raises SIGTERM, which ends the process
        current = read_server_info(state_dir)
        if current and current.get("pid") == os.getpid():
            with contextlib.suppress(OSError):
                (state_dir / "server.json").unlink()

    app = create_app(state_dir, workers=workers, grace_s=grace_s, on_shutdown=forget_address)
    server = uvicorn.Server(
        uvicorn.Config(
            app, log_level="warning", access_log=False, lifespan="on", timeout_graceful_shutdown=SHUTDOWN_GRACE_S
        )
    )
    url_host = f"[{host}]" if ":" in host else host
    info = {"url": f"http://{url_host}:{port}", "host": host, "port": port, "pid": os.getpid(), "state": str(state_dir)}

    def announce() -> None:
        while not server.started and not server.should_exit:
            time.sleep(0.05)
        if server.started:
            write_text_atomic(state_dir / "server.json", json.dumps(info) + "\n")
            print(
                f"forestreg service at {info['url']} (token in {state_dir / 'token'}; jobs in {state_dir / 'jobs.sqlite'})",
                file=sys.stderr,
                flush=True,
            )

    def idle_watch() -> None:
        manager: JobManager = app.state.manager
        while not server.should_exit:
            time.sleep(1.0)
            if not manager.busy() and time.monotonic() - manager.last_activity > idle_exit_s:
                print(f"forestreg serve: idle for {idle_exit_s:.0f} s, stopping", file=sys.stderr)
                server.should_exit = True

    def exit_watch() -> None:
        """Once asked to stop, the service ends within its grace even if a request or a job hangs:
        the jobs' process groups are killed, the address forgotten, the process ends (the OS
        releases the state folder's lock)."""
        while not server.should_exit:
            time.sleep(0.1)
        app.state.stopping.set()
        manager: JobManager = app.state.manager
        time.sleep(SHUTDOWN_GRACE_S + manager.grace_s + 10.0)
        with contextlib.suppress(Exception):
            manager.kill_all()
        with contextlib.suppress(Exception):
            forget_address()
        print("forestreg serve: stopped (a request or a job did not end in time)", file=sys.stderr, flush=True)
        os._exit(0)

    threading.Thread(target=announce, daemon=True).start()
    threading.Thread(target=exit_watch, daemon=True).start()
    if idle_exit_s:
        threading.Thread(target=idle_watch, daemon=True).start()
    try:
        server.run(sockets=[sock])
    finally:
        forget_address()
        lock.close()
    return 0
