"""The parts the result views (co-registration, re-survey, evaluation) are made of: a headline, a
read-only table of figures, two panes side by side or one above the other, the view's layout
(headline, button rows, the panes), the progress bar and Cancel button of a view's background task,
and the reading of a result table's cells by column name."""

from __future__ import annotations

from typing import Any, Callable, Optional, Sequence

from PySide6.QtCore import Qt
from PySide6.QtWidgets import (
    QAbstractItemView,
    QHeaderView,
    QLabel,
    QLayout,
    QProgressBar,
    QPushButton,
    QSplitter,
    QTableWidget,
    QVBoxLayout,
    QWidget,
)


def headline(text: str) -> QLabel:
    """The view's first line (rich text, wrapped)."""
    label = QLabel(text)
    label.setWordWrap(True)
    label.setStyleSheet("padding: 4px;")
    return label


def figures_table(headers: Sequence[str], *, stretch_last: bool = True) -> QTableWidget:
    """A read-only table with the column ``headers``: no row numbers, rows 22 px high, columns as
    wide as their contents (the last one stretched to the view's width when ``stretch_last``)."""
    table = QTableWidget(0, len(headers))
    table.setHorizontalHeaderLabels(list(headers))
    table.verticalHeader().setVisible(False)
    table.verticalHeader().setDefaultSectionSize(22)
    table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
    table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
    table.horizontalHeader().setStretchLastSection(stretch_last)
    return table


def two_panes(orientation: Qt.Orientation, first: QWidget, second: QWidget, sizes: Sequence[int]) -> QSplitter:
    """``first`` and ``second`` in a splitter the user can drag, at ``sizes`` pixels to start."""
    split = QSplitter(orientation)
    split.addWidget(first)
    split.addWidget(second)
    split.setSizes(list(sizes))
    return split


def lay_out_view(view: QWidget, top: QLabel, body: QWidget, rows: Optional[Sequence[QLayout]] = ()) -> QVBoxLayout:
    """``view``'s layout: the headline ``top``, the button ``rows``, then ``body`` taking the rest."""
    lay = QVBoxLayout(view)
    lay.setContentsMargins(4, 4, 4, 4)
    lay.addWidget(top)
    for row in rows or ():
        lay.addLayout(row)
    lay.addWidget(body, 1)
    return lay


class CellsByName:
    """A result table's cells by row and column name (for a ``QTableWidget`` whose ``column(name)``
    gives a column's index): the raw value each item keeps under ``Qt.UserRole`` (what the
    engine reported, not its formatting) and the text shown."""

    def value(self, row: int, name: str) -> Any:
        item = self.item(row, self.column(name))  # type: ignore[attr-defined]
        return None if item is None else item.data(Qt.ItemDataRole.UserRole)

    def text(self, row: int, name: str) -> str:
        item = self.item(row, self.column(name))  # type: ignore[attr-defined]
        return "" if item is None else item.text()


class TaskProgress:
    """A view's progress bar (0-1000) and its Cancel button (``on_cancel``), both hidden but while
    the view's one background task runs."""

    def __init__(self, on_cancel: Callable[[], Any]) -> None:
        self.bar = QProgressBar()
        self.bar.setRange(0, 1000)
        self.bar.hide()
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.hide()
        self.cancel_button.clicked.connect(on_cancel)

    def begin(self, what: str = "") -> None:
        """Show both, the bar at zero saying ``what``."""
        self.bar.setValue(0)
        if what:
            self.bar.setFormat(what)
        self.bar.show()
        self.cancel_button.show()

    def report(self, fraction: float, message: str) -> None:
        """The task's progress (a worker's ``progress(fraction, message)``)."""
        self.bar.setValue(int(1000 * fraction))
        self.bar.setFormat(f"{message} %p%")

    def end(self) -> None:
        self.bar.hide()
        self.cancel_button.hide()
