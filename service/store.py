"""The job store: one SQLite database (``DIR/jobs.sqlite``) holding every job and its events.

SQLite in WAL mode commits each state change durably, so the job list survives a crash or a
``kill -9`` of the service; on the next start :meth:`JobStore.recover` marks the jobs that were
running as ``interrupted`` (they can be resubmitted) and returns the queued ones to run again.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Optional

#: a job's states; ``done`` means the command ran to its end (exit 0, or 1 for an honest failure
#: such as a registration without enough evidence), ``error`` bad input (exit 2) or a crash
STATUSES = ("queued", "running", "done", "cancelled", "error", "interrupted")
FINAL = frozenset({"done", "cancelled", "error", "interrupted"})

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    seq INTEGER NOT NULL,
    args TEXT NOT NULL,
    cwd TEXT,
    status TEXT NOT NULL,
    progress REAL NOT NULL DEFAULT 0,
    step TEXT,
    message TEXT,
    exit_code INTEGER,
    result TEXT,
    result_path TEXT,
    outputs TEXT,
    pid INTEGER,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    cancel_requested INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS events (
    job_id TEXT NOT NULL,
    n INTEGER NOT NULL,
    data TEXT NOT NULL,
    PRIMARY KEY (job_id, n)
);
"""


class JobStore:
    """Thread-safe access to the jobs database (one connection, serialised by a lock)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.RLock()
        self._db = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None, timeout=30)
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)
        columns = {r["name"] for r in self._db.execute("PRAGMA table_info(jobs)")}
        if "outputs" not in columns:  # a database of an earlier service: the files each job wrote, as a column
            self._db.execute("ALTER TABLE jobs ADD COLUMN outputs TEXT")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # ----------------------------------------------------------------------------- writing

    def add(self, args: list[str], cwd: Optional[str]) -> str:
        job_id = uuid.uuid4().hex[:12]
        with self._lock:
            seq = (self._db.execute("SELECT COALESCE(MAX(seq), 0) FROM jobs").fetchone()[0] or 0) + 1
            self._db.execute(
                "INSERT INTO jobs (id, seq, args, cwd, status, progress, message, created) VALUES (?, ?, ?, ?, 'queued', 0, 'queued', ?)",
                (job_id, seq, json.dumps(args), cwd, time.time()),
            )
        self.add_event(job_id, {"event": "status", "status": "queued"})
        return job_id

    def update(self, job_id: str, **fields: Any) -> None:
        if not fields:
            return
        if "result" in fields and fields["result"] is not None and not isinstance(fields["result"], str):
            fields["result"] = json.dumps(fields["result"])
        cols = ", ".join(f"{k} = ?" for k in fields)
        with self._lock:
            self._db.execute(f"UPDATE jobs SET {cols} WHERE id = ?", (*fields.values(), job_id))

    def add_event(self, job_id: str, event: dict) -> int:
        with self._lock:
            n = (
                self._db.execute("SELECT COALESCE(MAX(n), 0) FROM events WHERE job_id = ?", (job_id,)).fetchone()[0]
                or 0
            ) + 1
            self._db.execute("INSERT INTO events (job_id, n, data) VALUES (?, ?, ?)", (job_id, n, json.dumps(event)))
        return n

    def claim_next(self) -> Optional[dict]:
        """The oldest queued job, now marked running (None when the queue is empty)."""
        with self._lock:
            row = self._db.execute("SELECT id FROM jobs WHERE status = 'queued' ORDER BY seq LIMIT 1").fetchone()
            if row is None:
                return None
            self._db.execute(
                "UPDATE jobs SET status = 'running', started = ?, message = 'starting' WHERE id = ?",
                (time.time(), row["id"]),
            )
        self.add_event(row["id"], {"event": "status", "status": "running"})
        return self.get(row["id"])

    def recover(self) -> list[dict]:
        """After a restart: jobs that were running are ``interrupted``; returns them."""
        with self._lock:
            rows = [dict(r) for r in self._db.execute("SELECT id, pid FROM jobs WHERE status = 'running'")]
            for r in rows:
                self._db.execute(
                    "UPDATE jobs SET status = 'interrupted', finished = ?, message = ? WHERE id = ?",
                    (time.time(), "interrupted: the service stopped while the job ran (resubmit it)", r["id"]),
                )
        for r in rows:
            self.add_event(r["id"], {"event": "status", "status": "interrupted"})
        return rows

    # ----------------------------------------------------------------------------- reading

    def get(self, job_id: str) -> Optional[dict]:
        with self._lock:
            row = self._db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return None if row is None else _public(row)

    def raw(self, job_id: str) -> Optional[dict]:
        with self._lock:
            row = self._db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return None if row is None else dict(row)

    def list(self, limit: int = 1000) -> list[dict]:
        with self._lock:
            rows = self._db.execute("SELECT * FROM jobs ORDER BY seq DESC LIMIT ?", (limit,)).fetchall()
        return [_public(r) for r in rows]

    def events(self, job_id: str, after: int = 0) -> list[tuple[int, dict]]:
        with self._lock:
            rows = self._db.execute(
                "SELECT n, data FROM events WHERE job_id = ? AND n > ? ORDER BY n", (job_id, after)
            ).fetchall()
        return [(r["n"], json.loads(r["data"])) for r in rows]

    def count(self, status: str) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM jobs WHERE status = ?", (status,)).fetchone()[0]


def _public(row: sqlite3.Row) -> dict:
    """A job as the API shows it."""
    result = row["result"]
    if result is not None:
        try:
            result = json.loads(result)
        except ValueError:
            pass
    return {
        "id": row["id"],
        "args": json.loads(row["args"]),
        "cwd": row["cwd"],
        "status": row["status"],
        "progress": row["progress"],
        "step": row["step"],
        "message": row["message"],
        "exit_code": row["exit_code"],
        "result": result,
        "result_path": row["result_path"],
        "outputs": json.loads(row["outputs"]) if row["outputs"] else [],
        "created": row["created"],
        "started": row["started"],
        "finished": row["finished"],
    }
