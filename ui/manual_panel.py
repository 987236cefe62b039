"""Widgets of manual mode: the per-scan targets table and the auto-vs-manual comparison view.

Both only show and edit what the engine keeps (``ScanEntry.targets``, the comparison dict of
:func:`forestreg.engine.tls.compare.compare_auto_manual`); the window's manual-mode mixin
(:mod:`forestreg.ui.manual_mode`) wires them to the project and the background workers.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Optional

import numpy as np
from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QBrush, QColor
from PySide6.QtWidgets import (
    QAbstractItemView,
    QComboBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QLineEdit,
    QPushButton,
    QSplitter,
    QTableWidget,
    QTableWidgetItem,
    QTextBrowser,
    QVBoxLayout,
    QWidget,
)

from ..app.comparison import ComparisonFigures
from .project_model import STATUS_COLOURS
from .results_tables import _fmt, _item, _num, _Table

TARGET_COLUMNS = ("Target", "x (m)", "y (m)", "z (m)")

COMPARE_COLUMNS = (
    "Pair (moving \u2192 reference)",
    "VOPs ref",
    "VOPs mov",
    "Matched VOPs",
    "ICP std auto (cm)",
    "ICP std manual (cm)",
    "Targets",
    "Rot. diff (\u00b0)",
    "Transl. diff (cm)",
    "Auto",
    "Manual",
)
COMPARE_TIPS = {
    "Matched VOPs": "Trunk shadows (VOPs) matched by the marker-free (proposed) method",
    "ICP std auto (cm)": "ICP standard deviation after the marker-free registration (paper table 4)",
    "ICP std manual (cm)": "ICP standard deviation after the target-based (manual) registration",
    "Targets": "Shared targets used by the manual registration",
    "Rot. diff (\u00b0)": "Angle between the two results (degrees)",
    "Transl. diff (cm)": "How far apart the two results put the moving scanner",
    "Auto": "Status of the marker-free (proposed) registration",
    "Manual": "Status of the target-based (manual) registration",
}
RESIDUAL_COLUMNS = ("Plot / target", "Auto (cm)", "Manual (cm)", "Targets seen twice")


def next_target_id(existing: Mapping[str, Any], prefix: str = "T") -> str:
    """The first ``prefix<n>`` (n = 1, 2, ...) not in ``existing``."""
    k = 1
    while f"{prefix}{k}" in existing:
        k += 1
    return f"{prefix}{k}"


class TargetsPanel(QWidget):
    """One scan's targets (id, x, y, z in its file coordinates), editable, with the manual-mode
    buttons. Emits :attr:`targetsEdited` (scan, new targets dict) when the user edits a cell; an
    invalid edit emits :attr:`editRejected` (reason) and the table shows the targets again."""

    targetsEdited = Signal(str, object)
    editRejected = Signal(str)
    scanChosen = Signal(str)

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(parent)
        self._loading = False
        self._targets: dict[str, np.ndarray] = {}
        self.scan_combo = QComboBox()
        self.scan_combo.setToolTip("The scan whose targets are listed (coordinates in that scan's own file)")
        self.scan_combo.currentTextChanged.connect(self._scan_changed)
        self.table = QTableWidget(0, len(TARGET_COLUMNS))
        self.table.setHorizontalHeaderLabels(list(TARGET_COLUMNS))
        self.table.verticalHeader().setVisible(False)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setAlternatingRowColors(True)
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.Stretch)
        self.table.itemChanged.connect(self._item_changed)
        self.table.itemSelectionChanged.connect(self._selection_changed)
        self.id_edit = QLineEdit()
        self.id_edit.setPlaceholderText("target id")
        self.id_edit.setMaximumWidth(110)
        self.id_edit.setToolTip("The id a picked point gets (an existing id is moved to the picked point)")
        b = self._button
        self.add_button = b("Add", "Add a target row (then type its coordinates, or pick it in the 3D view)")
        self.delete_button = b("Delete", "Delete the selected targets of this scan")
        self.pick_button = b(
            "Pick target",
            "Click a point of this scan in the 3D view (before registration) to place the target named in the id box",
        )
        self.pick_button.setCheckable(True)
        self.detect_button = b("Detect reflectors", "Find bright (high-reflectance) targets in this scan's intensity")
        self.import_button = b("Import CSV\u2026", "Read targets of all scans from a CSV (scan,target,x,y,z)")
        self.export_button = b("Export CSV\u2026", "Write the targets of all scans to a CSV (scan,target,x,y,z)")
        self.manual_all_button = b("All links manual", "Register every scan from its targets (manual method)")
        self.run_manual_button = b("Run manual registration", "Register the links set to manual from the targets")
        self.compare_button = b(
            "Compare auto vs manual", "Register the plot both ways and show the paper's tables 4 and 5"
        )
        self.info = QLabel("")
        self.info.setStyleSheet("color: #555;")
        self.info.setWordWrap(True)

        top = QHBoxLayout()
        top.addWidget(QLabel("Scan:"))
        top.addWidget(self.scan_combo, 1)
        top.addWidget(self.add_button)
        top.addWidget(self.delete_button)
        top.addWidget(QLabel("Id:"))
        top.addWidget(self.id_edit)
        top.addWidget(self.pick_button)
        top.addWidget(self.detect_button)
        second = QHBoxLayout()
        for w in (
            self.import_button,
            self.export_button,
            self.manual_all_button,
            self.run_manual_button,
            self.compare_button,
        ):
            second.addWidget(w)
        second.addStretch(1)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(4, 4, 4, 4)
        lay.addLayout(top)
        lay.addWidget(self.table, 1)
        lay.addWidget(self.info)
        lay.addLayout(second)
        self.add_button.clicked.connect(self._add_row)
        self.delete_button.clicked.connect(self._delete_rows)

    @staticmethod
    def _button(text: str, tip: str) -> QPushButton:
        button = QPushButton(text)
        button.setToolTip(tip)
        return button

    # ------------------------------------------------------------------ showing

    @property
    def scan(self) -> str:
        return self.scan_combo.currentText()

    def set_scans(self, names: list[str]) -> None:
        """The scans to choose from (keeps the chosen one when it is still there)."""
        current = self.scan
        self.scan_combo.blockSignals(True)
        self.scan_combo.clear()
        self.scan_combo.addItems(names)
        if current in names:
            self.scan_combo.setCurrentText(current)
        self.scan_combo.blockSignals(False)

    def select_scan(self, name: str) -> None:
        if name != self.scan:
            self.scan_combo.setCurrentText(name)

    def show_targets(self, targets: Mapping[str, Any], info: str = "") -> None:
        """Fill the table with one scan's targets."""
        self._targets = {str(k): np.asarray(v, dtype=float) for k, v in targets.items()}
        self._loading = True
        try:
            self.table.setRowCount(0)
            self.table.setRowCount(len(self._targets))
            for r, (tid, xyz) in enumerate(self._targets.items()):
                self.table.setItem(r, 0, QTableWidgetItem(tid))
                for c in range(3):
                    item = QTableWidgetItem(f"{xyz[c]:.4f}")
                    item.setData(Qt.ItemDataRole.UserRole, float(xyz[c]))
                    item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
                    self.table.setItem(r, c + 1, item)
        finally:
            self._loading = False
        self.info.setText(info)
        if not self.id_edit.text().strip() or self.id_edit.text().strip() in self._targets:
            self.id_edit.setText(next_target_id(self._targets))

    def target_ids(self) -> list[str]:
        return [self.table.item(r, 0).text() for r in range(self.table.rowCount())]

    def row_of(self, target_id: str) -> int:
        ids = self.target_ids()
        return ids.index(target_id) if target_id in ids else -1

    def value(self, row: int, column: str) -> Any:
        """A cell's value: the id (text) or a coordinate (float)."""
        item = self.table.item(row, TARGET_COLUMNS.index(column))
        if item is None:
            return None
        return item.text() if column == "Target" else item.data(Qt.ItemDataRole.UserRole)

    # ------------------------------------------------------------------ editing

    def _scan_changed(self, name: str) -> None:
        if name:
            self.scanChosen.emit(name)

    def _selection_changed(self) -> None:
        rows = sorted({i.row() for i in self.table.selectedIndexes()})
        if len(rows) == 1 and self.table.item(rows[0], 0) is not None:
            self.id_edit.setText(self.table.item(rows[0], 0).text())

    def _read_table(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for r in range(self.table.rowCount()):
            cells = [self.table.item(r, c) for c in range(4)]
            tid = cells[0].text().strip() if cells[0] is not None else ""
            if not tid:
                raise ValueError(f"row {r + 1}: the target id must not be empty")
            if tid in out:
                raise ValueError(f"target {tid!r} is listed twice")
            xyz = []
            for c, cell in zip("xyz", cells[1:]):
                text = cell.text().strip() if cell is not None else ""
                try:
                    v = float(text.replace(",", "."))
                except ValueError:
                    raise ValueError(f"target {tid}: {c} = {text!r} is not a number") from None
                if not math.isfinite(v):
                    raise ValueError(f"target {tid}: {c} must be a finite number")
                xyz.append(v)
            out[tid] = np.array(xyz)
        return out

    def _item_changed(self, item: QTableWidgetItem) -> None:
        if self._loading or not self.scan:
            return
        try:
            targets = self._read_table()
        except ValueError as exc:
            self.editRejected.emit(str(exc))
            QTimer.singleShot(0, lambda: self.show_targets(self._targets, self.info.text()))
            return
        scan = self.scan
        # after this signal: the project change rebuilds the table (and deletes this item)
        QTimer.singleShot(0, lambda: self.targetsEdited.emit(scan, targets))

    def _add_row(self) -> None:
        if not self.scan:
            return
        targets = dict(self._targets)
        tid = next_target_id(targets)
        targets[tid] = np.zeros(3)
        self.targetsEdited.emit(self.scan, targets)
        row = self.row_of(tid)
        if row >= 0:
            self.table.selectRow(row)
            self.id_edit.setText(tid)

    def _delete_rows(self) -> None:
        rows = {i.row() for i in self.table.selectedIndexes()}
        if not rows or not self.scan:
            return
        ids = self.target_ids()
        gone = {ids[r] for r in rows}
        self.targetsEdited.emit(self.scan, {k: v for k, v in self._targets.items() if k not in gone})


class ComparisonView(QWidget):
    """The auto-vs-manual comparison: the paper's table 4 (per pair) and table 5 (per plot) as
    tables, and the report's comparison section (with its figures) beside them."""

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(parent)
        self.comparison: Optional[dict[str, Any]] = None
        self.summary = QLabel(
            "Press \u201cCompare auto vs manual\u201d (Manual menu) to register the plot both ways: "
            "from trunk shadows and from the scans' targets."
        )
        self.summary.setWordWrap(True)
        self.pairs_table = _Table(COMPARE_COLUMNS)
        for k, name in enumerate(COMPARE_COLUMNS):
            if name in COMPARE_TIPS:
                self.pairs_table.horizontalHeaderItem(k).setToolTip(COMPARE_TIPS[name])
        self.pairs_table.horizontalHeader().setStretchLastSection(False)
        self.residual_table = _Table(RESIDUAL_COLUMNS)
        self.residual_table.horizontalHeader().setStretchLastSection(False)
        self.browser = QTextBrowser()
        self.browser.setOpenExternalLinks(True)
        self.browser.installEventFilter(self)
        left = QWidget()
        lay = QVBoxLayout(left)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.summary)
        lay.addWidget(QLabel("<b>Per pair</b> (paper table 4)"))
        lay.addWidget(self.pairs_table)
        lay.addWidget(
            QLabel(
                "<b>Per plot</b> (paper table 5): average distance between the centres of one target seen "
                "from different scans, then per target"
            )
        )
        lay.addWidget(self.residual_table, 1)
        split = QSplitter(Qt.Orientation.Horizontal)
        split.addWidget(left)
        split.addWidget(self.browser)
        split.setStretchFactor(0, 3)
        split.setStretchFactor(1, 2)
        self.splitter = split
        outer = QVBoxLayout(self)
        outer.setContentsMargins(4, 4, 4, 4)
        outer.addWidget(split)

    def eventFilter(self, watched: Any, event: Any) -> bool:  # noqa: N802 - Qt API
        from PySide6.QtCore import QEvent

        if watched is self.browser and event.type() == QEvent.Type.Resize:
            section = getattr(self, "_section", "")
            if section and abs(max(self.browser.viewport().width() - 24, 200) - self._figure_width) > 8:
                QTimer.singleShot(0, lambda: self._show_figures(section))  # the figures follow the panel's width
        return super().eventFilter(watched, event)

    def show_comparison(self, comparison: Mapping[str, Any]) -> None:
        from ..engine.report.plot_report import comparison_section

        self.comparison = dict(comparison)
        figures = ComparisonFigures.of(comparison)
        pairs = figures.pairs
        t = self.pairs_table
        t.setRowCount(0)
        t.setRowCount(len(pairs))
        for r, p in enumerate(pairs):
            a, m = p.auto, p.manual
            cells = [
                _item(f"{p.moving} \u2192 {p.reference}"),
                _item(a.reference_vops, None if a.reference_vops is not None else "\u2013"),
                _item(a.moving_vops, None if a.moving_vops is not None else "\u2013"),
                _item(a.matched, None if a.matched is not None else "\u2013"),
                _item(a.icp_std_m, _fmt(a.icp_std_m, 2, 100.0)),
                _item(m.icp_std_m, _fmt(m.icp_std_m, 2, 100.0)),
                _item(m.targets, None if m.targets is not None else "\u2013"),
                _item(p.rotation_difference_deg, _fmt(p.rotation_difference_deg, 3)),
                _item(p.translation_difference_m, _fmt(p.translation_difference_m, 2, 100.0)),
                _item(a.status, tip=a.reason),
                _item(m.status, tip=m.reason),
            ]
            for c in (9, 10):
                colour = STATUS_COLOURS.get(str(cells[c].text()))
                if colour:
                    cells[c].setForeground(QBrush(QColor(colour)))
            for c, cell in enumerate(cells):
                t.setItem(r, c, cell)
        t.resizeColumnsToContents()
        height = t.horizontalHeader().height() + 2 * t.frameWidth() + sum(t.rowHeight(r) for r in range(t.rowCount()))
        t.setMaximumHeight(height + t.horizontalScrollBar().sizeHint().height() + 6)
        t_auto, t_manual = figures.auto_targets, figures.manual_targets
        seen = len(set(t_auto) | set(t_manual))
        auto_r, manual_r = figures.auto_target_residual_m, figures.manual_target_residual_m
        rt = self.residual_table
        ids = sorted(set(t_auto) | set(t_manual), key=lambda i: (len(str(i)), str(i)))
        rt.setRowCount(0)
        rt.setRowCount(1 + len(ids))
        plot_row = [
            _item("average target residual"),
            _item(auto_r, _fmt(auto_r, 2, 100.0)),
            _item(manual_r, _fmt(manual_r, 2, 100.0)),
            _item(seen),
        ]
        for cell in plot_row:
            font = cell.font()
            font.setBold(True)
            cell.setFont(font)
        for c, cell in enumerate(plot_row):
            rt.setItem(0, c, cell)
        for r, tid in enumerate(ids, start=1):
            va, vm = t_auto.get(tid), t_manual.get(tid)
            for c, cell in enumerate(
                [_item(f"target {tid}"), _item(va, _fmt(va, 2, 100.0)), _item(vm, _fmt(vm, 2, 100.0)), _item("", "")]
            ):
                rt.setItem(r, c, cell)
        ok = sum(1 for p in pairs if p.auto.ok and p.manual.ok)
        text = f"{len(pairs)} pairs registered both ways, {ok} succeeded with both methods."
        if _num(auto_r) and _num(manual_r):
            text += (
                f" Average target residual: marker-free {100 * auto_r:.2f} cm, manual {100 * manual_r:.2f} cm "
                f"(difference {100 * (auto_r - manual_r):+.2f} cm)."
            )
        self.summary.setText(text)
        rt.resizeColumnsToContents()
        w = max(self.splitter.width(), 600)
        self.splitter.setSizes([int(0.6 * w), w - int(0.6 * w)])
        self._section = comparison_section(comparison)
        self._figure_width = 0
        self._show_figures(self._section)

    def _show_figures(self, section_html: str) -> None:
        """The report section's figures (PNG data URIs) with their captions, scaled to the browser."""
        import base64
        import re

        from PySide6.QtCore import QUrl
        from PySide6.QtGui import QImage, QTextDocument

        doc = self.browser.document()
        width = max(self.browser.viewport().width() - 24, 200)
        self._figure_width = width
        parts = ["<p><b>Figures</b> (paper tables 4 and 5; the same as in the HTML report)</p>"]
        for k, fig in enumerate(re.findall(r"<figure>(.*?)</figure>", section_html, flags=re.S)):
            caption = re.search(r"<figcaption>(.*?)</figcaption>", fig, flags=re.S)
            for j, src in enumerate(re.findall(r'src="data:image/png;base64,([^"]+)"', fig)):
                img = QImage.fromData(base64.b64decode(src), "PNG")
                if img.isNull():
                    continue
                url = QUrl(f"forestreg-figure://{k}-{j}.png")
                doc.addResource(QTextDocument.ResourceType.ImageResource, url, img)
                w = min(width, img.width())
                h = int(img.height() * w / img.width())
                if h > 320:  # two figures in view at once
                    w, h = int(w * 320 / h), 320
                parts.append(f'<p><img src="{url.toString()}" width="{w}" height="{h}"></p>')
            if caption:
                parts.append(f'<p style="color:#555">{caption.group(1)}</p>')
        self.browser.setHtml("".join(parts))
