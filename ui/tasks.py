"""Keeps the window's background workers alive until they end, and calls back in the GUI thread.

A worker's signals are emitted in its own thread. Connected to a plain Python function they would
run there too, so every callback goes through a small relay QObject that lives in the GUI thread:
Qt then queues the call to the GUI thread, where touching widgets is allowed.
"""

from __future__ import annotations

from typing import Any, Callable, Optional

from PySide6.QtCore import QObject, QThread, Signal, Slot

from .worker import TaskWorker, make_thread


class _Relay(QObject):
    """Receives one worker's signals in the GUI thread and calls the given functions."""

    def __init__(self, parent: QObject, callbacks: dict[str, Optional[Callable[..., Any]]]) -> None:
        super().__init__(parent)
        self.callbacks = callbacks

    def _call(self, name: str, *args: Any) -> None:
        fn = self.callbacks.get(name)
        if fn is not None:
            fn(*args)

    @Slot(float, str)
    def progress(self, fraction: float, message: str) -> None:
        self._call("progress", fraction, message)

    @Slot(object)
    def succeeded(self, result: Any) -> None:
        self._call("succeeded", result)

    @Slot(str, str)
    def failed(self, message: str, details: str) -> None:
        self._call("failed", message, details)

    @Slot()
    def cancelled(self) -> None:
        self._call("cancelled")

    @Slot(str)
    def link_done(self, name: str) -> None:
        self._call("link_done", name)

    @Slot()
    def ended(self) -> None:
        self._call("ended")


class TaskSet(QObject):
    """The running workers of one window. ``idle`` is emitted when the last one has ended."""

    idle = Signal()

    def __init__(self, parent: Optional[QObject] = None) -> None:
        super().__init__(parent)
        self._running: dict[int, tuple[TaskWorker, QThread, _Relay]] = {}

    def start(
        self,
        worker: TaskWorker,
        *,
        succeeded: Optional[Callable[[Any], None]] = None,
        failed: Optional[Callable[[str, str], None]] = None,
        cancelled: Optional[Callable[[], None]] = None,
        progress: Optional[Callable[[float, str], None]] = None,
        link_done: Optional[Callable[[str], None]] = None,
        ended: Optional[Callable[[], None]] = None,
    ) -> TaskWorker:
        """Start ``worker`` in its own thread; the callbacks run in the GUI thread."""
        key = id(worker)
        relay = _Relay(
            self,
            {
                "succeeded": succeeded,
                "failed": failed,
                "cancelled": cancelled,
                "progress": progress,
                "link_done": link_done,
                "ended": ended,
            },
        )
        worker.progress.connect(relay.progress)
        worker.succeeded.connect(relay.succeeded)
        worker.failed.connect(relay.failed)
        worker.cancelled.connect(relay.cancelled)
        if hasattr(worker, "link_done"):
            worker.link_done.connect(relay.link_done)
        thread = make_thread(worker)
        self._running[key] = (worker, thread, relay)
        relay.callbacks["ended"] = lambda: self._ended(key, ended)
        thread.finished.connect(relay.ended)
        thread.start()
        return worker

    def _ended(self, key: int, ended: Optional[Callable[[], None]]) -> None:
        entry = self._running.pop(key, None)
        if entry is not None:
            entry[1].deleteLater()
            entry[2].deleteLater()
        if ended is not None:
            ended()
        if not self._running:
            # no run of this window writes now: a run that failed after checking its output
            # folder keeps no other process out of it
            from ..app.common import release_output_locks

            release_output_locks()
            self.idle.emit()

    def busy(self, name: Optional[str] = None) -> bool:
        """Whether any worker (or one with this name) is still running."""
        return any(name is None or w.name == name for w, _, _ in self._running.values())

    def cancel_all(self) -> None:
        for worker, _, _ in list(self._running.values()):
            worker.cancel()

    def wait_all(self, timeout_ms: int = 30000) -> bool:
        """Block until every thread has ended (at window close); True when all did."""
        ok = True
        for _, thread, _ in list(self._running.values()):
            ok &= thread.wait(timeout_ms)
        return ok
