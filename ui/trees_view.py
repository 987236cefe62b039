"""The trees view: a plot map linked to a sortable table of every tree and measure, and the
selected tree in 3D (its cylinder model, its stem circles, the points around it) with its stem
curve. It shows a ``forestreg trees --out DIR`` folder read by
:func:`forestreg.app.trees.read_trees_folder`; nothing is measured here.

Flagged trees (incomplete, failed fits, ...) are drawn red on the map and their rows are tinted,
with the engine's reason in the "Flag" column and as tooltip.
"""

from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Ellipse
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QBrush, QColor
from PySide6.QtWidgets import (
    QAbstractItemView,
    QDoubleSpinBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPushButton,
    QSizePolicy,
    QSplitter,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from ..engine.io.results import TreesOutput, trees_output_from_inventory
from .panes import CellsByName, TaskProgress
from .scene_view import SceneView, add_guides
from .worker import TaskWorker

FLAG_COLOUR = "#d92d20"
OK_COLOUR = "#1f7a3f"
SELECT_COLOUR = "#1d4ed8"
EDIT_COLOUR = "#7c3aed"
STEM_COLOUR = "#8c5a2b"
BRANCH_COLOUR = "#c9a36b"

#: Known trees.csv columns: (column, header, scale, digits, tooltip). Others (e.g. quality
#: figures added later) follow with their own names.
KNOWN_COLUMNS: tuple[tuple[str, str, float, int, str], ...] = (
    ("dbh_m", "DBH (cm)", 100.0, 1, "Stem diameter at breast height (1.3 m above the ground), from circle fits"),
    (
        "height_m",
        "Height (m)",
        1.0,
        1,
        'Tree height above the ground model: its highest point, or an estimate where that point is not the tree\'s top: the plot\'s height-diameter curve (marked "(curve)") or the tallest its stem stands ("(slenderness)"), the reason in its tip',
    ),
    (
        "height_points_m",
        "Highest point (m)",
        1.0,
        1,
        "The tree's highest point above the ground model, whether or not it was taken as the height",
    ),
    ("crown_base_m", "Crown base (m)", 1.0, 1, "Height of the lowest live crown above the ground"),
    ("crown_width_ew_m", "Crown E-W (m)", 1.0, 1, "Crown width east-west"),
    ("crown_width_ns_m", "Crown N-S (m)", 1.0, 1, "Crown width north-south"),
    ("crown_area_m2", "Crown area (m\u00b2)", 1.0, 1, "Projected crown area"),
    ("crown_volume_m3", "Crown volume (m\u00b3)", 1.0, 1, "Crown volume (convex hull)"),
    ("volume_m3", "Wood volume (m\u00b3)", 1.0, 3, "Volume of the cylinder model (stem and branches)"),
    ("stem_volume_m3", "Stem volume (m\u00b3)", 1.0, 3, "Volume of the stem cylinders"),
    ("branch_volume_m3", "Branch volume (m\u00b3)", 1.0, 3, "Volume of the branch cylinders"),
    ("qsm_dbh_m", "DBH from cylinders (cm)", 100.0, 1, "DBH of the cylinder model (a check on the circle fit)"),
    ("n_cylinders", "Cylinders", 1.0, 0, "Cylinders in the tree's model"),
    ("n_branches", "Branches", 1.0, 0, "Branches in the tree's model"),
    ("lean_deg", "Lean (\u00b0)", 1.0, 1, "Stem lean from the vertical"),
    (
        "dbh_arc_coverage",
        "DBH arc seen",
        1.0,
        2,
        "Share of the stem's circumference with points at breast height (1 = all round)",
    ),
    ("dbh_rms_mm", "DBH fit rms (mm)", 1.0, 1, "Root mean square distance of the points from the fitted circle"),
    ("n_points", "Points", 1.0, 0, "Points of the tree"),
    ("wood_fraction", "Wood share", 1.0, 2, "Share of the tree's points classed as wood"),
)
HIDDEN = {"tree_id", "x", "y", "z", "flag"}


class _NumberItem(QTableWidgetItem):
    """A cell that sorts by its raw value (NaN last), not by its text."""

    def __lt__(self, other: QTableWidgetItem) -> bool:  # noqa: D105
        a, b = self.data(Qt.ItemDataRole.UserRole), other.data(Qt.ItemDataRole.UserRole)
        try:
            fa, fb = float(a), float(b)
        except (TypeError, ValueError):
            return str(a) < str(b)
        if math.isnan(fa):
            return False
        if math.isnan(fb):
            return True
        return fa < fb


def _cell(value: Any, text: str, tip: str = "") -> QTableWidgetItem:
    item = _NumberItem(text)
    item.setData(Qt.ItemDataRole.UserRole, value)
    item.setFlags(Qt.ItemFlag.ItemIsEnabled | Qt.ItemFlag.ItemIsSelectable)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
    if tip:
        item.setToolTip(tip)
    return item


class TreeTable(CellsByName, QTableWidget):
    """One row per tree; click a header to sort. Raw values under ``Qt.UserRole``."""

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(0, 0, parent)
        self.columns: list[tuple[str, str, float, int, str]] = []
        self.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.setAlternatingRowColors(True)
        self.verticalHeader().setVisible(False)
        self.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)

    def show_trees(self, out: TreesOutput) -> None:
        self.setSortingEnabled(False)
        known = [c for c in KNOWN_COLUMNS if c[0] in out.columns]
        names = {c[0] for c in KNOWN_COLUMNS}
        extra = [
            (c, c, 1.0, 3, f"{c} (as written by the trees engine)")
            for c in out.numeric_columns
            if c not in names and c not in HIDDEN
        ]
        self.columns = (
            [("tree_id", "Tree", 1.0, 0, "Tree id in trees.csv (\u26a0 flagged, \u270e edited by hand)")]
            + known
            + extra
            + [("flag", "Flag", 1.0, 0, "Why the engine flagged the tree (empty: complete and measured)")]
        )
        self.clear()
        self.setColumnCount(len(self.columns))
        self.setHorizontalHeaderLabels([c[1] for c in self.columns])
        for k, c in enumerate(self.columns):
            self.horizontalHeaderItem(k).setToolTip(c[4])
        self.setRowCount(len(out.trees))
        tint = QBrush(QColor("#fde8e7"))
        edit_tint = QBrush(QColor("#efe7fd"))
        for r, t in enumerate(out.trees):
            for k, (name, _, scale, digits, _) in enumerate(self.columns):
                if name == "tree_id":
                    text = ("\u26a0 " if t.flagged else "") + str(t.tree_id) + (" \u270e" if t.edited else "")
                    tip = "; ".join(x for x in (t.flag.strip(), f"edited: {t.edited}" if t.edited else "") if x)
                    item = _cell(t.tree_id, text, tip=tip)
                    if t.flagged:
                        item.setForeground(QBrush(QColor(FLAG_COLOUR)))
                elif name == "flag":
                    flag = t.flag.strip()
                    item = _cell(flag, flag, tip=flag)
                    if flag:
                        item.setForeground(QBrush(QColor(FLAG_COLOUR)))
                elif name == "height_m" and t.height_source != "points":
                    # predicted from the plot's height-diameter curve: marked, the reason in the tip
                    v = t.get(name)
                    item = _cell(v, f"{v * scale:.{digits}f} ({t.height_source})", tip=t.quality("height"))
                else:
                    v = t.get(name)
                    text = "\u2013" if not math.isfinite(v) else f"{v * scale:.{digits}f}"
                    item = _cell(v, text)
                if t.flagged:
                    item.setBackground(tint)
                elif t.edited:
                    item.setBackground(edit_tint)
                self.setItem(r, k, item)
        self.setSortingEnabled(True)
        self.horizontalHeader().setStretchLastSection(True)

    def column(self, name: str) -> int:  # type: ignore[override]
        """The index of a column by its name in trees.csv."""
        return [c[0] for c in self.columns].index(name)

    def row_of(self, tree_id: int) -> int:
        c = self.column("tree_id")
        for r in range(self.rowCount()):
            if self.item(r, c).data(Qt.ItemDataRole.UserRole) == tree_id:
                return r
        return -1

    def selected_tree(self) -> Optional[int]:
        rows = self.selectionModel().selectedRows() if self.selectionModel() else []
        return None if not rows else int(self.value(rows[0].row(), "tree_id"))


class _FigurePanel(QWidget):
    """A widget filled by one matplotlib figure (``figure``, drawn on ``canvas``) of ``size`` inches."""

    def __init__(self, size: float, parent: Optional[QWidget] = None) -> None:
        super().__init__(parent)
        self.figure = Figure(figsize=(size, size), dpi=90, layout="constrained")
        self.canvas = FigureCanvasQTAgg(self.figure)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.canvas)


class TreeMap(_FigurePanel):
    """The plot map: stems (dot size ~ DBH), crowns (ellipses from the E-W and N-S widths),
    flagged trees red, the selected tree blue. A click selects the nearest tree."""

    treeClicked = Signal(int)
    positionClicked = Signal(float, float)  # file coordinates (m)

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(4, parent)
        self.out: Optional[TreesOutput] = None
        self.selected: Optional[int] = None
        self.origin = np.zeros(2)
        self.canvas.mpl_connect("button_press_event", self._clicked)

    def show_trees(self, out: TreesOutput, selected: Optional[int] = None) -> None:
        self.out, self.selected = out, selected
        self.figure.clear()
        ax = self.figure.add_subplot()
        xy = np.array([[t.x, t.y] for t in out.trees], dtype=float).reshape(-1, 2)
        good = np.isfinite(xy).all(axis=1)
        self.origin = np.floor(np.nanmin(xy[good], axis=0)) if good.any() else np.zeros(2)
        n_flag = 0
        for t in out.trees:
            if not (math.isfinite(t.x) and math.isfinite(t.y)):
                continue
            x, y = t.x - self.origin[0], t.y - self.origin[1]
            colour = FLAG_COLOUR if t.flagged else (EDIT_COLOUR if t.edited else OK_COLOUR)
            n_flag += t.flagged
            ew, ns = t.get("crown_width_ew_m"), t.get("crown_width_ns_m")
            if math.isfinite(ew) and math.isfinite(ns) and ew > 0 and ns > 0:
                ax.add_patch(Ellipse((x, y), ew, ns, fill=True, fc=colour, alpha=0.10, ec=colour, lw=0.8, zorder=1))
            dbh = t.get("dbh_m")
            size = 12 + 220 * (dbh if math.isfinite(dbh) else 0.1)
            ax.scatter(
                [x], [y], s=size, c=colour, marker="X" if t.flagged else "o", edgecolors="k", linewidths=0.5, zorder=3
            )
            ax.annotate(
                str(t.tree_id), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7, color="0.2", zorder=4
            )
            if t.tree_id == selected:
                ax.scatter(
                    [x], [y], s=size + 220, facecolors="none", edgecolors=SELECT_COLOUR, linewidths=2.2, zorder=5
                )
        if good.any():
            lo, hi = np.nanmin(xy[good], axis=0) - self.origin - 3.0, np.nanmax(xy[good], axis=0) - self.origin + 3.0
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal", adjustable="box")
        ax.grid(True, lw=0.3, color="0.85", zorder=0)
        ax.set_xlabel(f"E (m, + {self.origin[0]:.0f})", fontsize=8)
        ax.set_ylabel(f"N (m, + {self.origin[1]:.0f})", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(f"{len(out.trees)} trees, {n_flag} flagged: click one", fontsize=9)
        handles = [
            Line2D([], [], ls="none", marker="o", ms=7, mfc=OK_COLOUR, mec="k", label="measured"),
            Line2D([], [], ls="none", marker="X", ms=8, mfc=FLAG_COLOUR, mec="k", label="flagged"),
            Line2D([], [], ls="none", marker="o", ms=10, mfc="none", mec=SELECT_COLOUR, mew=2, label="selected"),
        ]
        if any(t.edited for t in out.trees):
            handles.append(Line2D([], [], ls="none", marker="o", ms=7, mfc=EDIT_COLOUR, mec="k", label="edited"))
        self.figure.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize=7, frameon=False)
        self.canvas.draw_idle()

    def _clicked(self, event: Any) -> None:
        if self.out is None or event.inaxes is None or event.xdata is None:
            return
        self.positionClicked.emit(float(event.xdata + self.origin[0]), float(event.ydata + self.origin[1]))
        xy = np.array([[t.x, t.y] for t in self.out.trees]) - self.origin
        d = np.hypot(xy[:, 0] - event.xdata, xy[:, 1] - event.ydata)
        d[~np.isfinite(d)] = np.inf
        if len(d) and np.isfinite(d.min()):
            self.treeClicked.emit(int(self.out.trees[int(np.argmin(d))].tree_id))


class StemCurvePlot(_FigurePanel):
    """Diameter against height of the selected tree (accepted fits, interpolated ones, rejected
    raw fits) with the DBH at 1.3 m."""

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(3, parent)

    def show_tree(self, out: Optional[TreesOutput], tree_id: Optional[int]) -> None:
        self.figure.clear()
        ax = self.figure.add_subplot()
        curve = out.curves.get(int(tree_id)) if out is not None and tree_id is not None else None
        if curve is None or not len(curve.height_m):
            ax.set_axis_off()
            ax.text(
                0.5, 0.5, "No stem curve for this tree", ha="center", va="center", color="0.4", transform=ax.transAxes
            )
            self.canvas.draw_idle()
            return
        h, d = curve.height_m, 100.0 * curve.diameter_m
        fit = curve.accepted & ~curve.interpolated & np.isfinite(d)
        interp = curve.interpolated & np.isfinite(d)
        raw = ~curve.accepted & np.isfinite(curve.raw_diameter_m)
        ax.plot(d[np.isfinite(d)], h[np.isfinite(d)], color=STEM_COLOUR, lw=1.0, zorder=1)
        ax.scatter(d[fit], h[fit], s=18, color=STEM_COLOUR, zorder=3, label="fitted")
        if interp.any():
            ax.scatter(
                d[interp], h[interp], s=18, facecolors="white", edgecolors=STEM_COLOUR, zorder=3, label="interpolated"
            )
        if raw.any():
            ax.scatter(
                100.0 * curve.raw_diameter_m[raw],
                h[raw],
                s=14,
                marker="x",
                color="0.55",
                zorder=2,
                label="rejected fit",
            )
        dbh = out.tree(int(tree_id)).get("dbh_m")
        if math.isfinite(dbh):
            ax.scatter(
                [100 * dbh], [1.3], s=60, marker="D", color=SELECT_COLOUR, zorder=4, label=f"DBH {100 * dbh:.1f} cm"
            )
        ax.set_xlabel("diameter (cm)", fontsize=8)
        ax.set_ylabel("height above ground (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_xlim(left=0)
        ax.grid(True, lw=0.3, color="0.85")
        ax.set_title(f"Stem curve of tree {tree_id}", fontsize=9)
        ax.legend(fontsize=7, loc="upper right", framealpha=0.85)
        self.canvas.draw_idle()


def cylinder_mesh(model: Any, *, stem_only: bool = False) -> Any:
    """One mesh of all cylinders of a :class:`~forestreg.engine.trees.qsm.CylinderModel`, with a
    ``branch_order`` cell array (0 = stem)."""
    import pyvista as pv

    parts = []
    for k in range(len(model)):
        if stem_only and model.branch_order[k] != 0:
            continue
        r, length = float(model.radius_m[k]), float(model.length_m[k])
        if not (r > 0 and length > 0 and np.isfinite(model.start[k]).all()):
            continue
        centre = model.start[k] + 0.5 * length * model.axis[k]
        cyl = pv.Cylinder(center=centre, direction=model.axis[k], radius=r, height=length, resolution=14, capping=True)
        cyl.cell_data["branch_order"] = np.full(cyl.n_cells, int(model.branch_order[k]))
        parts.append(cyl)
    if not parts:
        return None
    return pv.merge(parts) if len(parts) > 1 else parts[0]


def stem_circles(curve: Any) -> list[Any]:
    """Circles (pyvista polylines) of the stem curve's diameters at their centres."""
    import pyvista as pv

    out = []
    t = np.linspace(0.0, 2.0 * np.pi, 33)
    for c, d, interp in zip(curve.centres, curve.diameter_m, curve.interpolated):
        if not (np.isfinite(c).all() and np.isfinite(d) and d > 0):
            continue
        ring = np.column_stack([c[0] + 0.5 * d * np.cos(t), c[1] + 0.5 * d * np.sin(t), np.full(len(t), c[2])])
        out.append((pv.lines_from_points(ring), bool(interp)))
    return out


def points_near(points: Optional[np.ndarray], trees_xy: np.ndarray, index: int, radius_m: float) -> np.ndarray:
    """Points (file coordinates) within ``radius_m`` of tree ``index`` horizontally that lie nearer
    to it than to any other tree: the points around a tree, not the engine's segmentation."""
    if points is None or not len(points):
        return np.zeros((0, 3))
    c = trees_xy[index]
    d = np.hypot(points[:, 0] - c[0], points[:, 1] - c[1])
    near = points[d <= radius_m]
    if not len(near) or len(trees_xy) < 2:
        return near
    from scipy.spatial import cKDTree

    good = np.isfinite(trees_xy).all(axis=1)
    ids = np.flatnonzero(good)
    _, nearest = cKDTree(trees_xy[good]).query(near[:, :2])
    return near[ids[nearest] == index]


class TreesView(QWidget):
    """Map + table (left) and the selected tree in 3D + its stem curve (right), and the correction
    loop: measure a cloud here, then delete / merge / split / add a stem / DBH at a height, undo,
    save (:mod:`forestreg.engine.trees.edit` does the work, in a worker)."""

    treeSelected = Signal(int)
    edited = Signal(str)  # the note of the edit done
    editFailed = Signal(str)

    def __init__(
        self, parent: Optional[QWidget] = None, renderer: Optional[str] = None, start_task: Optional[Any] = None
    ) -> None:
        super().__init__(parent)
        self.out: Optional[TreesOutput] = None
        self.points: Optional[np.ndarray] = None
        self.selected: Optional[int] = None
        self._start_task = start_task
        from ..engine.params import TreeParams

        self.params = TreeParams()
        self.inventory: Any = None  # a TreeInventory measured in this session (edits need it)
        self.local_points: Optional[np.ndarray] = None
        self.base_inventory: Any = None
        self.steps: list[tuple[Any, Any]] = []  # (TreeEdit, inventory after it)
        self.pending: Optional[str] = None
        self.worker: Optional[TaskWorker] = None
        self.last_error: Optional[str] = None
        self.map = TreeMap()
        self.table = TreeTable()
        self.scene3d = SceneView(renderer=renderer)
        self.curve = StemCurvePlot()
        self.info = QLabel(
            "Open a trees result folder (File \u25b8 Open trees result\u2026), made by 'forestreg trees --out DIR'."
        )
        self.info.setWordWrap(True)
        self.info.setStyleSheet("padding: 4px; color: #344054;")
        left = QSplitter(Qt.Orientation.Vertical)
        left.addWidget(self.map)
        left.addWidget(self.table)
        left.setSizes([380, 260])
        right = QSplitter(Qt.Orientation.Vertical)
        right.addWidget(self.scene3d)
        right.addWidget(self.curve)
        right.setSizes([420, 220])
        split = QSplitter(Qt.Orientation.Horizontal)
        split.addWidget(left)
        split.addWidget(right)
        split.setSizes([560, 520])
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.info)
        lay.addLayout(self._edit_bar())
        lay.addWidget(split, 1)
        self.map.treeClicked.connect(self._map_tree_clicked)
        self.map.positionClicked.connect(self._map_position_clicked)
        self.table.itemSelectionChanged.connect(self._table_selected)

    def _edit_bar(self) -> QHBoxLayout:
        bar = QHBoxLayout()
        bar.setContentsMargins(4, 0, 4, 0)

        def button(text: str, tip: str, slot: Any) -> QPushButton:
            b = QPushButton(text)
            b.setToolTip(tip)
            b.clicked.connect(lambda checked=False: slot())
            bar.addWidget(b)
            return b

        self.measure_button = button(
            "Measure trees\u2026", "Measure the trees of a cloud here (needed to correct them)", self._ask_measure
        )
        self.delete_button = button("Delete", "Delete the selected tree (a false stem)", self.delete_selected)
        self.merge_button = button(
            "Merge with\u2026",
            "Merge the selected tree with the next tree you click on the map",
            lambda: self._arm("merge"),
        )
        self.split_button = button(
            "Split at\u2026", "Split the selected tree: click the second stem on the map", lambda: self._arm("split")
        )
        self.add_button = button("Add stem\u2026", "Add a missed stem: click it on the map", lambda: self._arm("add"))
        self.dbh_height = QDoubleSpinBox()
        self.dbh_height.setRange(0.3, 5.0)
        self.dbh_height.setSingleStep(0.1)
        self.dbh_height.setValue(1.3)
        self.dbh_height.setSuffix(" m")
        self.dbh_height.setToolTip("Height along the stem at which the DBH is measured (above a buttress)")
        bar.addWidget(QLabel("DBH at"))
        bar.addWidget(self.dbh_height)
        self.dbh_button = button(
            "Apply",
            "Measure the selected tree's DBH at this height",
            lambda: self.dbh_height_selected(self.dbh_height.value()),
        )
        self.undo_button = button("Undo", "Undo the last edit", self.undo)
        self.save_button = button(
            "Save\u2026",
            "Write the edited trees (trees.csv with an 'edited' column, edits.json, report)",
            self._ask_save,
        )
        self.edit_status = QLabel("")
        self.edit_status.setStyleSheet("color: #475467;")
        # a long message must not widen the window (1280 px screens)
        self.edit_status.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
        self.edit_status.setMinimumWidth(40)
        bar.addWidget(self.edit_status, 1)
        self.edit_task = TaskProgress(lambda: self.worker.cancel() if self.worker is not None else None)
        self.edit_progress, self.edit_cancel = self.edit_task.bar, self.edit_task.cancel_button
        self.edit_progress.setMaximumWidth(220)
        bar.addWidget(self.edit_progress)
        bar.addWidget(self.edit_cancel)
        self._update_edit_buttons()
        return bar

    def _update_edit_buttons(self) -> None:
        busy = self.worker is not None
        can = self.inventory is not None and not busy
        sel = can and self.selected is not None
        self.measure_button.setEnabled(not busy)
        for b in (self.delete_button, self.merge_button, self.split_button, self.dbh_button):
            b.setEnabled(sel)
        self.add_button.setEnabled(can)
        self.undo_button.setEnabled(can and bool(self.steps))
        self.save_button.setEnabled(can and bool(self.steps))
        if self.inventory is None and not busy:
            self.edit_status.setText("To correct trees, measure them here (Measure trees\u2026).")

    # ------------------------------------------------------------------ background work

    def _work(self, what: str, fn: Any, done: Any) -> bool:
        if self._start_task is None or self.worker is not None:
            return False
        self.last_error = None
        worker = TaskWorker(fn, name=f"trees: {what}")
        self.worker = worker
        self.edit_task.begin()
        self.edit_status.setText(f"{what}\u2026")
        self._update_edit_buttons()

        def failed(message: str, details: str) -> None:
            self.last_error = message
            self.edit_status.setText(f"<span style='color:{FLAG_COLOUR}'>{what}: {message}</span>")
            self.editFailed.emit(message)

        def ended() -> None:
            self.worker = None
            self.edit_task.end()
            self._update_edit_buttons()

        self._start_task(
            worker,
            succeeded=done,
            failed=failed,
            cancelled=lambda: self.edit_status.setText(f"{what}: cancelled"),
            progress=self.edit_task.report,
            ended=ended,
        )
        return True

    def _ask_measure(self) -> None:
        from PySide6.QtWidgets import QFileDialog

        path, _ = QFileDialog.getOpenFileName(
            self,
            "Cloud to measure (ground-based or fused)",
            "",
            "Point clouds (*.las *.laz *.ply *.pcd *.xyz *.txt *.e57)",
        )
        if path:
            self.measure(path)

    def measure(self, cloud: str) -> bool:
        """Measure the trees of a cloud file in a worker; then they can be corrected."""
        params = self.params

        def task(progress: Any, cancel: Any) -> tuple[Any, np.ndarray]:
            from ..app.trees import measure_trees_file
            from ..engine.core.errors import ScanDataError

            progress(0.0, "reading the cloud")
            # the command line's use case, on the same file with the same parameters; nothing written
            outcome = measure_trees_file(cloud, None, params, progress=progress, cancel=cancel)
            if not outcome:  # the data do not allow trees: said as the window says any failure
                raise ScanDataError(outcome.reason)
            return outcome.result, outcome.points

        def done(result: tuple[Any, np.ndarray]) -> None:
            inv, pts = result
            self.local_points = pts
            self.base_inventory = inv
            self.steps = []
            self._set_inventory(inv, note=f"measured {len(inv.trees)} trees in {cloud}")

        return self._work("Measuring the trees", task, done)

    def _notes(self) -> dict[int, str]:
        from ..app.trees import edit_notes

        return edit_notes(self.base_inventory, self.steps) if self.base_inventory is not None else {}

    def _set_inventory(self, inv: Any, note: str = "") -> None:
        self.inventory = inv
        shift = np.asarray(inv.origin_shift, dtype=np.float64)
        out = trees_output_from_inventory(inv, self._notes(), self.out.folder if self.out is not None else "")
        keep = self.selected
        self.show_output(out, self.local_points + shift if self.local_points is not None else None, select=keep)
        if note:
            self.edit_status.setText(note + (f"  ({len(self.steps)} edit(s); Undo to go back)" if self.steps else ""))
        self._update_edit_buttons()

    # ------------------------------------------------------------------ edits

    def _to_local(self, x: float, y: float) -> tuple[float, float]:
        shift = np.asarray(self.inventory.origin_shift, dtype=np.float64)
        return float(x - shift[0]), float(y - shift[1])

    def apply(self, edit: Any) -> bool:
        """Apply a :class:`~forestreg.engine.trees.edit.TreeEdit` in a worker (only its trees are
        measured again); False when no inventory is there or work is running."""
        if self.inventory is None or self.local_points is None:
            return False
        inv, pts, params = self.inventory, self.local_points, self.params

        def task(progress: Any, cancel: Any) -> Any:
            from ..app.trees import apply_tree_edit

            progress(0.1, edit.describe())
            return apply_tree_edit(pts, inv, edit, params)

        def done(after: Any) -> None:
            self.steps.append((edit, after))
            if edit.kind in ("add", "split"):
                new = sorted({r.tree_id for r in after.trees} - {r.tree_id for r in inv.trees})
                if new:
                    self.selected = new[-1]
            elif edit.kind == "delete":
                self.selected = None
            self._set_inventory(
                after, note=f"{edit.describe()} (tree {edit.trees[0] if edit.trees else self.selected})"
            )
            self.edited.emit(edit.describe())

        return self._work(edit.describe(), task, done)

    def delete_selected(self) -> bool:
        from ..app.trees import edit as TreeEdit

        return self.selected is not None and self.apply(TreeEdit("delete", (self.selected,)))

    def merge_selected_with(self, other: int) -> bool:
        from ..app.trees import edit as TreeEdit

        return self.selected is not None and self.apply(TreeEdit("merge", (self.selected, int(other))))

    def split_selected_at(self, x: float, y: float) -> bool:
        """Split the selected tree at the second stem near (x, y) (file coordinates)."""
        from ..app.trees import edit as TreeEdit

        return (
            self.selected is not None
            and self.inventory is not None
            and self.apply(TreeEdit("split", (self.selected,), xy=self._to_local(x, y)))
        )

    def add_stem_at(self, x: float, y: float) -> bool:
        """Add the stem near (x, y) (file coordinates)."""
        from ..app.trees import edit as TreeEdit

        return self.inventory is not None and self.apply(TreeEdit("add", (), xy=self._to_local(x, y)))

    def dbh_height_selected(self, height_m: float) -> bool:
        from ..app.trees import edit as TreeEdit

        return self.selected is not None and self.apply(
            TreeEdit("dbh_height", (self.selected,), height_m=float(height_m))
        )

    def undo(self) -> bool:
        """Go back one edit."""
        if not self.steps or self.worker is not None:
            return False
        edit, _ = self.steps.pop()
        inv = self.steps[-1][1] if self.steps else self.base_inventory
        self._set_inventory(inv, note=f"undone: {edit.describe()}")
        self.edited.emit(f"undone: {edit.describe()}")
        return True

    def save_edits(self, folder: str) -> Any:
        """Write the edited inventory (engine's writer; trees.csv marks edited trees; edits.json)."""
        from ..app.trees import save_edited

        return save_edited(folder, self.inventory, self._notes(), [e for e, _ in self.steps], self.local_points)

    def _ask_save(self) -> None:
        from PySide6.QtWidgets import QFileDialog

        folder = QFileDialog.getExistingDirectory(self, "Folder for the edited trees")
        if folder:
            try:
                path = self.save_edits(folder)
                self.edit_status.setText(f"saved {path}")
            except Exception as exc:  # noqa: BLE001 - tell the user, keep the edits
                self.edit_status.setText(f"<span style='color:{FLAG_COLOUR}'>cannot save: {exc}</span>")

    def _arm(self, action: str) -> None:
        self.pending = action
        text = {
            "merge": "Click the tree to merge into the selected one",
            "split": "Click the second stem of the selected tree",
            "add": "Click the missed stem on the map",
        }[action]
        self.edit_status.setText(text + " (Esc: cancel)")

    def _map_position_clicked(self, x: float, y: float) -> None:
        action, self.pending = self.pending, None
        if action == "split":
            self.split_selected_at(x, y)
        elif action == "add":
            self.add_stem_at(x, y)
        elif action == "merge":
            self._merge_pending = True

    def _map_tree_clicked(self, tree_id: int) -> None:
        if getattr(self, "_merge_pending", False):
            self._merge_pending = False
            if tree_id != self.selected:
                self.merge_selected_with(tree_id)
            return
        if self.worker is None:
            self.select_tree(tree_id)

    def keyPressEvent(self, event: Any) -> None:  # noqa: N802 - Qt API
        if event.key() == Qt.Key.Key_Escape and self.pending:
            self.pending = None
            self.edit_status.setText("")
            return
        super().keyPressEvent(event)

    # ------------------------------------------------------------------ loading

    def show_output(
        self, out: TreesOutput, points: Optional[np.ndarray] = None, *, select: Optional[int] = None
    ) -> None:
        """Show a trees folder; ``points`` (N, 3, file coordinates) the measured cloud, optional."""
        self.out = out
        self.points = None if points is None else np.asarray(points, dtype=np.float64)
        n_flag = sum(t.flagged for t in out.trees)
        n_edit = sum(bool(t.edited) for t in out.trees)
        text = f"<b>{out.folder}</b>: {len(out.trees)} trees, {n_flag} flagged (red)"
        if n_edit:
            text += f", {n_edit} edited by hand (violet)"
        if self.points is None:
            text += ". Without the cloud (--cloud) only the models are drawn in 3D."
        self.info.setText(text)
        self.table.show_trees(out)
        if hasattr(self, "measure_button"):
            self._update_edit_buttons()
        if not out.trees:
            self.map.show_trees(out)
            self.scene3d.show_scene(None, message="No tree in this result")
            self.curve.show_tree(None, None)
            return
        keep = select if select is not None and any(t.tree_id == select for t in out.trees) else out.trees[0].tree_id
        self.selected = None
        self.select_tree(keep)

    # ------------------------------------------------------------------ selection

    def _table_selected(self) -> None:
        tid = self.table.selected_tree()
        if tid is not None and tid != self.selected:
            self.select_tree(tid)

    def select_tree(self, tree_id: int) -> None:
        """Select a tree: highlight it on the map and in the table, draw it in 3D and its curve."""
        if self.out is None:
            return
        self.selected = int(tree_id)
        row = self.table.row_of(self.selected)
        if row >= 0 and self.table.selected_tree() != self.selected:
            self.table.blockSignals(True)
            self.table.selectRow(row)
            self.table.blockSignals(False)
            self.table.scrollToItem(self.table.item(row, 0))
        self.map.show_trees(self.out, self.selected)
        self.curve.show_tree(self.out, self.selected)
        self._draw_3d()
        self._update_edit_buttons()
        self.treeSelected.emit(self.selected)

    def _draw_3d(self) -> None:
        import pyvista as pv

        out, tid = self.out, self.selected
        assert out is not None and tid is not None
        tree = out.tree(tid)
        index = [t.tree_id for t in out.trees].index(tid)
        trees_xy = np.array([[t.x, t.y] for t in out.trees], dtype=float)
        widths = [tree.get("crown_width_ew_m"), tree.get("crown_width_ns_m")]
        radius = max([w / 2.0 for w in widths if math.isfinite(w)] + [1.5])
        near = points_near(self.points, trees_xy, index, radius + 0.5)
        if len(near) and math.isfinite(tree.z):  # the ground around the foot hides the stem
            near = near[near[:, 2] > tree.z + 0.3]
        model = out.cylinders(tid)
        curve = out.curves.get(tid)
        # draw around the tree's foot (file coordinates can be UTM: float32 would lose centimetres)
        shift = np.array([tree.x, tree.y, tree.z if math.isfinite(tree.z) else 0.0])
        if not np.isfinite(shift).all():
            shift = np.zeros(3)

        def paint(pl: Any) -> None:
            legend = []
            if len(near):
                local = near - shift
                cloud = pv.PolyData(local.astype(np.float32))
                pl.add_mesh(cloud, color="#5b8c51", point_size=1.5, style="points", name="tree-points", opacity=0.3)
                legend.append((f"{len(near):,} points around the tree (green)", "#3f7d3a"))
            if model is not None and len(model):
                shifted = _shifted(model, shift)
                stem = cylinder_mesh(shifted, stem_only=True)
                allc = cylinder_mesh(shifted)
                if allc is not None:
                    branches = allc.threshold(0.5, scalars="branch_order") if stem is not None else allc
                    if branches is not None and branches.n_cells:
                        pl.add_mesh(branches, color=BRANCH_COLOUR, name="branches", smooth_shading=True)
                if stem is not None:
                    pl.add_mesh(stem, color=STEM_COLOUR, name="stem", smooth_shading=True)
                legend.append((f"cylinder model: {len(model)} cylinders (stem brown, branches tan)", STEM_COLOUR))
            if curve is not None:
                moved = _with_centres(curve, curve.centres - shift)
                for k, (ring, interp) in enumerate(stem_circles(moved)):
                    pl.add_mesh(ring, color="#f59e0b" if interp else SELECT_COLOUR, line_width=3, name=f"ring{k}")
                legend.append(("stem circles (blue fitted, amber interpolated)", SELECT_COLOUR))
            if not legend:
                pl.add_text(
                    f"Tree {tid}: nothing to draw (no cylinder model, no stem curve, no cloud)",
                    position="upper_left",
                    font_size=10,
                    color="#444444",
                )
                return
            title = f"Tree {tid}"
            dbh, height = tree.get("dbh_m"), tree.get("height_m")
            if math.isfinite(dbh):
                title += f"   DBH {100 * dbh:.1f} cm"
            if math.isfinite(height):
                title += f"   height {height:.1f} m" + (
                    f" ({tree.height_source})" if tree.height_source != "points" else ""
                )
            if tree.flagged:
                title += "   \u26a0 flagged"
            pl.add_text(
                title,
                position="upper_left",
                font_size=10,
                color=FLAG_COLOUR if tree.flagged else "#222222",
                name="title",
            )
            pl.add_text(
                "\n".join(t for t, _ in legend), position="upper_right", font_size=9, color="#333333", name="legend"
            )
            r = max(radius, 1.0)
            ztop = height if math.isfinite(height) else 10.0
            add_guides(pl, (-r, r, -r, r, 0.0, ztop))

        self.scene3d.draw(paint, camera="side")


def _shifted(model: Any, shift: np.ndarray) -> Any:
    import dataclasses

    return dataclasses.replace(model, start=model.start - shift)


def _with_centres(curve: Any, centres: np.ndarray) -> Any:
    import dataclasses

    return dataclasses.replace(curve, centres=centres)
