"""Background work for the GUI: a registration run (and any other long engine call) in a QThread.

A worker is a QObject moved to its own :class:`QThread`; it calls the engine there and reports
through signals, which Qt delivers to the GUI thread (queued), so the window stays responsive.
Cancelling sets the engine's :class:`~forestreg.engine.core.progress.CancelToken`; the engine raises
:class:`~forestreg.engine.core.errors.Cancelled` at its next check and the worker emits ``cancelled``.

The engine leaves a project untouched by a failed or cancelled run except for the links that
had already finished; the worker adds nothing to that.
"""

from __future__ import annotations

import logging
import traceback
from typing import Any, Callable, Optional

from PySide6.QtCore import QObject, Qt, QThread, Signal, Slot

from ..engine.core.errors import Cancelled, ForestregError
from ..engine.core.progress import CancelToken

log = logging.getLogger("forestreg")

#: ``fn(progress, cancel)`` run by a :class:`TaskWorker`; its return value is emitted.
TaskFunction = Callable[[Callable[[float, str], None], CancelToken], Any]


def describe_error(exc: BaseException) -> tuple[str, str]:
    """A readable message and the technical details (traceback) of an exception.

    forestreg's own errors already say what went wrong and what to do; anything else is a bug or
    an environment problem, so its type is named too.
    """
    details = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    if isinstance(exc, ForestregError):
        return str(exc), details
    if isinstance(exc, MemoryError):
        return "The computer ran out of memory. Try fewer or thinned scans.", details
    if isinstance(exc, OSError):
        return f"A file could not be read or written: {exc}", details
    return f"Unexpected error ({type(exc).__name__}): {exc}", details


class TaskWorker(QObject):
    """Runs ``fn(progress, cancel)`` once, in whatever thread the worker lives in.

    Signals: ``progress(fraction, message)``, ``succeeded(result)``, ``failed(message, details)``,
    ``cancelled()``, and ``done()`` after any of the last three.
    """

    progress = Signal(float, str)
    succeeded = Signal(object)
    failed = Signal(str, str)
    cancelled = Signal()
    done = Signal()

    def __init__(self, fn: TaskFunction, name: str = "task") -> None:
        super().__init__()
        self.fn = fn
        self.name = name
        self.token = CancelToken()

    def cancel(self) -> None:
        """Ask the engine to stop at its next check (callable from any thread)."""
        self.token.cancel()

    def _report(self, fraction: float, message: str) -> None:
        self.token.raise_if_cancelled()
        self.progress.emit(float(fraction), str(message))

    def _call(self) -> Any:
        return self.fn(self._report, self.token)

    @Slot()
    def run(self) -> None:
        """Do the work and emit exactly one of succeeded / failed / cancelled, then done."""
        try:
            result = self._call()
        except Cancelled:
            log.info("%s cancelled", self.name)
            self.cancelled.emit()
        except BaseException as exc:  # noqa: BLE001 - every error must reach the user
            message, details = describe_error(exc)
            log.error("%s failed: %s", self.name, message)
            self.failed.emit(message, details)
        else:
            self.succeeded.emit(result)
        self.done.emit()


class RegistrationWorker(TaskWorker):
    """Registers a project through the plot use case's registration (:func:`~forestreg.app.plot.register_plot`:
    the scans checked first, the links, the global adjustment where links close loops, the project
    saved when it has a file).

    Extra signals: ``link_done(moving_scan_name)`` after each link, ``finished(outcome)`` with the
    engine's :class:`~forestreg.engine.tls.plot.PlotOutcome` (also emitted as ``succeeded``).
    """

    link_done = Signal(str)
    finished = Signal(object)

    def __init__(self, project: Any, scans: Any = None, *, rerun: bool = False) -> None:
        super().__init__(self._register, name="registration")
        self.project = project
        self.scans = scans
        self.rerun = rerun
        self.succeeded.connect(self.finished)

    def _register(self, progress: Callable[[float, str], None], cancel: CancelToken) -> Any:
        from ..app.plot import register_plot

        return register_plot(
            self.project,
            self.scans,
            rerun=self.rerun,
            progress=progress,
            cancel=cancel,
            on_link=lambda link: self.link_done.emit(link.moving),
        )


def make_thread(worker: TaskWorker, parent: Optional[QObject] = None) -> QThread:
    """A QThread (not started yet) that runs ``worker`` and quits when it is done; ``worker`` is
    moved to it. Connect to ``thread.finished`` before ``thread.start()``: a quick worker may end
    at once.
    """
    thread = QThread(parent)
    thread.setObjectName(f"forestreg-{worker.name}")
    worker.moveToThread(thread)
    thread.started.connect(worker.run)
    # direct: quit from the worker's thread, so a GUI thread blocked in wait() is not needed
    worker.done.connect(thread.quit, Qt.ConnectionType.DirectConnection)
    return thread


def start_worker(worker: TaskWorker, parent: Optional[QObject] = None) -> QThread:
    """Move ``worker`` to a new QThread and start it (keep references to both until the
    thread's ``finished``)."""
    thread = make_thread(worker, parent)
    thread.start()
    return thread
