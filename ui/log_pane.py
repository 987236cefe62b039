"""The log pane: the "forestreg" logger's records, shown as they come (from any thread)."""

from __future__ import annotations

import logging
from typing import Optional

from PySide6.QtCore import QObject, Signal
from PySide6.QtGui import QColor, QTextCharFormat
from PySide6.QtWidgets import QPlainTextEdit, QWidget

LOGGER = "forestreg"
LEVEL_COLOURS = {logging.WARNING: "#9a6700", logging.ERROR: "#b42318", logging.CRITICAL: "#b42318"}


class _Bridge(QObject):
    record = Signal(int, str)


class QtLogHandler(logging.Handler):
    """A logging handler that hands formatted records to the GUI thread through a signal."""

    def __init__(self) -> None:
        super().__init__(level=logging.INFO)
        self.bridge = _Bridge()
        self.setFormatter(logging.Formatter("%(asctime)s  %(levelname)-7s %(message)s", "%H:%M:%S"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.bridge.record.emit(record.levelno, self.format(record))
        except RuntimeError:  # the pane is gone (window closed while a worker logs)
            pass
        except Exception:  # noqa: BLE001 - logging must never raise
            self.handleError(record)


class LogPane(QPlainTextEdit):
    """Read-only text of the log; attaches a :class:`QtLogHandler` to the "forestreg" logger
    (and detaches it in :meth:`detach`, called when the window closes)."""

    def __init__(self, parent: Optional[QWidget] = None, *, max_lines: int = 5000) -> None:
        super().__init__(parent)
        self.setReadOnly(True)
        self.setMaximumBlockCount(max_lines)
        self.setPlaceholderText("Messages of the registration appear here.")
        self.handler = QtLogHandler()
        self.handler.bridge.record.connect(self.append_record)
        logger = logging.getLogger(LOGGER)
        if logger.level == logging.NOTSET or logger.level > logging.INFO:
            logger.setLevel(logging.INFO)
        logger.addHandler(self.handler)

    def append_record(self, level: int, text: str) -> None:
        """Append one line, coloured by level."""
        fmt = QTextCharFormat()
        if level in LEVEL_COLOURS:
            fmt.setForeground(QColor(LEVEL_COLOURS[level]))
        cursor = self.textCursor()
        cursor.movePosition(cursor.MoveOperation.End)
        if not self.document().isEmpty():
            cursor.insertBlock()
        cursor.insertText(text, fmt)
        self.ensureCursorVisible()

    def detach(self) -> None:
        """Stop receiving log records."""
        logging.getLogger(LOGGER).removeHandler(self.handler)
