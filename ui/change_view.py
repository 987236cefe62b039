"""The re-survey view: a ``forestreg change`` folder shown as its change map and its table of trees.

The headline says whether AFTER was registered onto BEFORE (with the uncertainty) and counts the
trees per status; the map (drawn by :func:`forestreg.engine.report.change_report.change_map_png`,
BEFORE file coordinates) colours persisting trees by DBH growth and marks removed and new trees;
the table lists every tree (filterable by status) with its changes and flags. Nothing is computed
here but the layout: the folder is read with :func:`forestreg.engine.io.change.read_change_dir` and its
result with :class:`forestreg.app.change.ChangeSummary`.
"""

from __future__ import annotations

import math
from typing import Any, Optional

from PySide6.QtCore import Qt
from PySide6.QtGui import QPixmap
from PySide6.QtWidgets import (
    QAbstractItemView,
    QComboBox,
    QHBoxLayout,
    QLabel,
    QSizePolicy,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from ..app.change import ROW_FILTERS, ChangeSummary, change_rows
from .panes import figures_table, headline, lay_out_view, two_panes

#: Table columns: (header, row key, scale, decimals).
COLUMNS = (
    ("Status", "status", None, 0),
    ("x", "x", 1.0, 2),
    ("y", "y", 1.0, 2),
    ("DBH before (cm)", "dbh_before_m", 100.0, 1),
    ("DBH after (cm)", "dbh_after_m", 100.0, 1),
    ("DBH change (mm)", "dbh_change_m", 1000.0, 1),
    ("\u00b1 (mm)", "dbh_change_sigma_m", 1000.0, 1),
    ("Height before (m)", "height_before_m", 1.0, 1),
    ("Height after (m)", "height_after_m", 1.0, 1),
    ("Height change (m)", "height_change_m", 1.0, 2),
    ("Flag", "flag", None, 0),
)
FILTERS = ROW_FILTERS


class ChangeView(QWidget):
    """Headline, change map and tree table of one re-survey comparison."""

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(parent)
        self.output: Any = None
        self.headline = headline(
            "Compare two surveys of one plot: run 'forestreg change BEFORE AFTER --out DIR', "
            "then File \u25b8 Open re-survey result\u2026"
        )
        self.map = QLabel()
        self.map.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self.map.setMinimumSize(200, 200)
        self.map.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self._pixmap: Optional[QPixmap] = None
        self.filter = QComboBox()
        self.filter.addItems(list(FILTERS))
        self.filter.currentTextChanged.connect(lambda _: self._fill_table())
        self.table = figures_table([c[0] for c in COLUMNS])
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        right = QWidget()
        rl = QVBoxLayout(right)
        rl.setContentsMargins(0, 0, 0, 0)
        row = QHBoxLayout()
        row.addWidget(QLabel("Show:"))
        row.addWidget(self.filter)
        row.addStretch(1)
        rl.addLayout(row)
        rl.addWidget(self.table, 1)
        lay_out_view(self, self.headline, two_panes(Qt.Orientation.Horizontal, self.map, right, (520, 680)))

    # ------------------------------------------------------------------ content

    def show_output(self, output: Any) -> None:
        """Show a :class:`~forestreg.engine.io.change.ChangeOutput` (a folder read back)."""
        from ..engine.report.change_report import change_map_png

        self.output = output
        summary = ChangeSummary.of(output.result)
        if summary.ok:
            how = (
                f" (\u00b1 {100 * summary.translation_m:.1f} cm, {summary.rotation_deg:.3f}\u00b0)"
                if summary.translation_m is not None and summary.rotation_deg is not None
                else ""
            )
            stems = "?" if summary.persisting_stems is None else summary.persisting_stems
            text = (
                f"<b>AFTER registered onto BEFORE</b>{how} from {stems} persisting stems: {summary.persisting} persisting, "
                f"{summary.removed} removed, {summary.new} new"
                + (f", {summary.outside} outside the other survey" if summary.outside else "")
            )
        else:
            text = f"<b style='color:#b42318'>Not compared:</b> {summary.reason}"
        self.headline.setText(text)
        rows = output.rows
        if rows:
            png = change_map_png(rows, title="change map (BEFORE file coordinates)")
            pix = QPixmap()
            pix.loadFromData(png, "PNG")
            self._pixmap = pix
        else:
            self._pixmap = None
            self.map.setText("no trees to show")
        self._scale_map()
        self._fill_table()

    def shown_rows(self) -> list[dict]:
        """The rows the table shows under the current filter."""
        return change_rows(self.output.rows if self.output is not None else [], self.filter.currentText())

    def _fill_table(self) -> None:
        rows = self.shown_rows()
        self.table.setRowCount(len(rows))
        for i, r in enumerate(rows):
            for j, (_, key, scale, digits) in enumerate(COLUMNS):
                v = r.get(key, "")
                if scale is None:
                    text = str(v or "")
                else:
                    try:
                        f = float(v)
                    except (TypeError, ValueError):
                        f = math.nan
                    text = "" if not math.isfinite(f) else f"{f * scale:.{digits}f}"
                item = QTableWidgetItem(text)
                if scale is not None:
                    item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
                if key == "flag" and text:
                    item.setToolTip(text)
                self.table.setItem(i, j, item)

    def _scale_map(self) -> None:
        if self._pixmap is not None and not self._pixmap.isNull():
            self.map.setPixmap(
                self._pixmap.scaled(
                    self.map.size(), Qt.AspectRatioMode.KeepAspectRatio, Qt.TransformationMode.SmoothTransformation
                )
            )

    def resizeEvent(self, event: Any) -> None:  # noqa: N802 - Qt's name
        super().resizeEvent(event)
        self._scale_map()
