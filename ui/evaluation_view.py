"""The field-data evaluation view: tree tables (e.g. ground-only and fused) compared with field
records by the engine's :func:`~forestreg.engine.trees.evaluate.evaluate` (R2, RMSE, rRMSE, bias per
parameter, detection), side by side, with one scatter per parameter (estimate against field, 1:1
line). Nothing is computed here but the layout."""

from __future__ import annotations

import math
from typing import Any, Mapping, Optional

from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.figure import Figure
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QTableWidgetItem, QWidget

from .panes import figures_table, headline, lay_out_view, two_panes

RUN_COLOURS = ("#b45309", "#1d4ed8", "#15803d", "#7c3aed")
COLUMNS = ("Run", "Parameter", "n", "R\u00b2", "RMSE", "rRMSE (%)", "Bias")


class EvaluationView(QWidget):
    """Statistics table (one row per run and parameter) and scatter plots."""

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(parent)
        self.runs: dict[str, Any] = {}
        self.headline = headline(
            "Compare tree tables with field records: File \u25b8 Evaluate against field data\u2026"
        )
        self.table = figures_table(COLUMNS, stretch_last=False)
        tips = {
            "R\u00b2": "coefficient of determination against the field values",
            "RMSE": "root mean square error (parameter unit)",
            "rRMSE (%)": "RMSE relative to the field mean",
            "Bias": "mean of estimate minus field (parameter unit)",
            "n": "matched trees with both values",
        }
        for k, c in enumerate(COLUMNS):
            if c in tips:
                self.table.horizontalHeaderItem(k).setToolTip(tips[c])
        self.figure = Figure(figsize=(6, 3), dpi=90, layout="constrained")
        self.canvas = FigureCanvasQTAgg(self.figure)
        lay_out_view(self, self.headline, two_panes(Qt.Orientation.Vertical, self.table, self.canvas, (190, 520)))

    def show_evaluations(self, runs: Mapping[str, Any], field_name: str = "field data") -> None:
        """``runs``: name -> :class:`~forestreg.engine.trees.evaluate.Evaluation`."""
        self.runs = dict(runs)
        parts = []
        for name, ev in runs.items():
            d = ev.detection
            parts.append(
                f"<b>{name}</b>: {d.matched} of {d.field_trees} field trees matched, {d.omitted} missed, "
                f"{d.commission} extra"
            )
        self.headline.setText(f"Against {field_name}: " + "; ".join(parts))
        rows = [(name, s) for name, ev in runs.items() for s in ev.stats.values()]
        order = {name: k for k, name in enumerate(runs)}
        rows.sort(key=lambda r: (r[1].parameter, order[r[0]]))  # each parameter's runs side by side
        self.table.setRowCount(len(rows))
        for r, (name, s) in enumerate(rows):
            info = s.info
            scale, unit = (100.0, "cm") if info.unit == "m" and s.parameter == "dbh_m" else (1.0, info.unit)
            cells = [
                (name, name),
                (s.parameter, f"{info.label} ({unit})"),
                (s.n, str(s.n)),
                (s.r2, _f(s.r2, 3)),
                (s.rmse, _f(s.rmse * scale, 2)),
                (s.rrmse_percent, _f(s.rrmse_percent, 1)),
                (s.bias, _f(s.bias * scale, 2)),
            ]
            for c, (value, text) in enumerate(cells):
                item = QTableWidgetItem(text)
                item.setData(Qt.ItemDataRole.UserRole, value)
                if c >= 2:
                    item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
                self.table.setItem(r, c, item)
        self._draw(runs)

    def value(self, run: str, parameter: str, column: str) -> Any:
        """The raw figure of one run and parameter (tests)."""
        k = COLUMNS.index(column)
        for r in range(self.table.rowCount()):
            if (
                self.table.item(r, 0).data(Qt.ItemDataRole.UserRole) == run
                and self.table.item(r, 1).data(Qt.ItemDataRole.UserRole) == parameter
            ):
                return self.table.item(r, k).data(Qt.ItemDataRole.UserRole)
        raise KeyError((run, parameter))

    def _draw(self, runs: Mapping[str, Any]) -> None:
        self.figure.clear()
        params = [
            p
            for p in ("dbh_m", "height_m", "volume_m3", "crown_area_m2", "crown_base_m", "crown_volume_m3")
            if any(p in ev.stats and ev.stats[p].n for ev in runs.values())
        ][:4]
        if not params:
            ax = self.figure.add_subplot()
            ax.set_axis_off()
            ax.text(
                0.5, 0.5, "No parameter in common with the field data", ha="center", va="center", transform=ax.transAxes
            )
            self.canvas.draw_idle()
            return
        axes = self.figure.subplots(1, len(params), squeeze=False)[0]
        for ax, p in zip(axes, params):
            lo, hi = math.inf, -math.inf
            label = ""
            for k, (name, ev) in enumerate(runs.items()):
                s = ev.stats.get(p)
                if s is None or not s.n:
                    continue
                scale = 100.0 if p == "dbh_m" else 1.0
                e, f = s.estimate * scale, s.field_value * scale
                ax.scatter(
                    f,
                    e,
                    s=16,
                    color=RUN_COLOURS[k % len(RUN_COLOURS)],
                    alpha=0.8,
                    label=f"{name}: R\u00b2 {_f(s.r2, 2)}, rRMSE {_f(s.rrmse_percent, 1)} %",
                )
                lo, hi = min(lo, f.min(), e.min()), max(hi, f.max(), e.max())
                label = s.info.label + (" (cm)" if p == "dbh_m" else f" ({s.info.unit})")
            if math.isfinite(lo):
                pad = 0.05 * (hi - lo or 1.0)
                ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="0.5", lw=0.8, ls="--", zorder=0)
                ax.set_xlim(lo - pad, hi + pad)
                ax.set_ylim(lo - pad, hi + pad)
            ax.set_aspect("equal")
            ax.set_xlabel(f"field {label}", fontsize=8)
            ax.set_ylabel(f"estimated {label}", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(True, lw=0.3, color="0.85")
            ax.legend(fontsize=6, loc="upper left", framealpha=0.85)
        self.canvas.draw_idle()


def _f(v: Any, digits: int) -> str:
    return f"{v:.{digits}f}" if isinstance(v, (int, float)) and math.isfinite(v) else "\u2013"
