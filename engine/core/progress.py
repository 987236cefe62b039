"""Progress reporting and cancellation for long-running engine work.

The engine never prints progress itself. Long functions take an optional ``progress`` callable
``progress(fraction, message)`` with ``fraction`` in [0, 1], and an optional :class:`CancelToken`.
The CLI turns the callbacks into a progress bar on stderr; the GUI into a progress dialog.
"""

from __future__ import annotations

import threading
from typing import Callable, Optional

from .errors import Cancelled

ProgressCallback = Callable[[float, str], None]


class CancelToken:
    """A thread-safe flag that a caller sets to ask a running operation to stop.

    The operation checks it between steps (:meth:`raise_if_cancelled`) and raises
    :class:`~forestreg.engine.core.errors.Cancelled`; nothing it already wrote is lost.
    """

    def __init__(self) -> None:
        self._event = threading.Event()

    def cancel(self) -> None:
        """Ask the running operation to stop at its next check."""
        self._event.set()

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()

    def raise_if_cancelled(self) -> None:
        if self._event.is_set():
            raise Cancelled("cancelled by the user")


class Progress:
    """Maps the steps of one operation onto a sub-range of a caller's progress callback.

    ``Progress(callback, start, stop)`` reports ``fraction`` in [0, 1] of this operation as
    ``start + fraction * (stop - start)`` to ``callback``; :meth:`sub` makes a nested range for a
    sub-step. A missing callback or token makes every call a no-op.
    """

    def __init__(
        self,
        callback: Optional[ProgressCallback] = None,
        start: float = 0.0,
        stop: float = 1.0,
        cancel: Optional[CancelToken] = None,
    ) -> None:
        self.callback = callback
        self.start = start
        self.stop = stop
        self.cancel = cancel

    def __call__(self, fraction: float, message: str = "") -> None:
        if self.cancel is not None:
            self.cancel.raise_if_cancelled()
        if self.callback is not None:
            f = min(max(fraction, 0.0), 1.0)
            self.callback(self.start + f * (self.stop - self.start), message)

    def sub(self, start: float, stop: float) -> "Progress":
        """A nested progress covering [start, stop] of this one (both in [0, 1])."""
        span = self.stop - self.start
        return Progress(self.callback, self.start + start * span, self.start + stop * span, self.cancel)


def as_progress(progress: "Optional[Progress | ProgressCallback]") -> Progress:
    """A :class:`Progress` from a Progress, a plain ``callback(fraction, message)`` or None."""
    if isinstance(progress, Progress):
        return progress
    return Progress(progress)
