"""The 2D top view: each scan's slice, its trunk shadows (VOPs), the scanners and the matched VOP
pairs, in the project frame, from the engine's :func:`compute_top_view` (nothing is recomputed
here; this only draws). Zoom and pan with the matplotlib toolbar."""

from __future__ import annotations

from typing import Mapping, Optional

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg, NavigationToolbar2QT
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle
from PySide6.QtWidgets import QSizePolicy, QVBoxLayout, QWidget

from ..engine.tls.views import TopView

MATCH_COLOUR = "#2ca02c"


def _lighter(colour: str, amount: float) -> tuple[float, float, float]:
    r, g, b = to_rgb(colour)
    return (r + (1 - r) * amount, g + (1 - g) * amount, b + (1 - b) * amount)


class TopViewWidget(QWidget):
    """A matplotlib canvas with its navigation toolbar showing a :class:`TopView`."""

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(parent)
        self.figure = Figure(figsize=(5, 5), dpi=90, layout="constrained")
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.toolbar = NavigationToolbar2QT(self.canvas, self)
        # the toolbar must not force the view wider than its pane (that clipped the map's right edge)
        self.toolbar.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Fixed)
        self.toolbar.setMinimumWidth(0)
        self.canvas.setMinimumSize(200, 200)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.toolbar)
        lay.addWidget(self.canvas, 1)
        self.view: Optional[TopView] = None
        self.show_message("Run the registration to see the slices, trunk shadows (VOPs) and matches.")

    def show_message(self, text: str) -> None:
        """An empty view with a sentence in it."""
        self.view = None
        self.figure.clear()
        ax = self.figure.add_subplot()
        ax.set_axis_off()
        ax.text(0.5, 0.5, text, ha="center", va="center", wrap=True, fontsize=11, color="0.35", transform=ax.transAxes)
        self.canvas.draw_idle()

    def show_view(self, view: TopView, colours: Mapping[str, str], title: str = "") -> None:
        """Draw slices, VOPs (circles), VOP radius, scanners (triangles) and matched pairs (green)."""
        self.view = view
        self.figure.clear()
        ax = self.figure.add_subplot()
        if not view.scans:
            ax.set_axis_off()
            ax.text(0.5, 0.5, "No registered scan to draw yet.", ha="center", va="center", transform=ax.transAxes, color="0.35")
            self.canvas.draw_idle()
            return
        o = view.origin[:2]
        drawn = sum(len(sv.slice_xy) for sv in view.scans.values())
        size = float(np.clip(40000.0 / max(drawn, 1), 0.5, 4.0))
        handles = []
        for name, sv in view.scans.items():
            colour = colours.get(name, "#555555")
            xy = sv.slice_xy - o
            ax.scatter(xy[:, 0], xy[:, 1], s=size, color=_lighter(colour, 0.25), alpha=0.6, linewidths=0, rasterized=True, zorder=1)
            v = sv.vops_xy - o
            ax.scatter(v[:, 0], v[:, 1], s=26, facecolors="none", edgecolors=colour, linewidths=1.1, zorder=3)
            c = sv.scanner[:2] - o
            ax.add_patch(Circle(tuple(c), sv.radius_m, fill=False, ls=(0, (4, 4)), color=colour, lw=0.7, alpha=0.6, zorder=2))
            ax.plot(c[0], c[1], marker="^", ms=11, mfc=colour, mec="k", mew=1.0, ls="none", zorder=6)
            ax.annotate(name, xy=(c[0], c[1]), xytext=(7, 7), textcoords="offset points", fontsize=8, zorder=7,
                        bbox=dict(boxstyle="round,pad=0.2", fc="white", ec=colour, lw=1.0, alpha=0.85))
            handles.append(Line2D([], [], ls="none", marker="o", ms=6, mfc="none", mec=colour, mew=1.4,
                                  label=f"{name}: {len(sv.vops_xy)} trunk shadows (within {sv.radius_m:.0f} m)"))
        n_pairs = 0
        for lv in view.links:
            if not len(lv.pairs):
                continue
            n_pairs += len(lv.pairs)
            a, b = lv.pairs[:, 0] - o, lv.pairs[:, 1] - o
            mid = (a + b) / 2
            ax.scatter(mid[:, 0], mid[:, 1], s=90, facecolors="none", edgecolors=MATCH_COLOUR, linewidths=1.6, zorder=4)
        handles.append(Line2D([], [], ls="none", marker="o", ms=9, mfc="none", mec=MATCH_COLOUR, mew=1.6,
                              label=f"matched trunk shadows ({n_pairs})"))
        allxy = np.concatenate([sv.slice_xy for sv in view.scans.values()] + [sv.scanner[None, :2] for sv in view.scans.values()]) - o
        if len(allxy):
            lo, hi = np.percentile(allxy, 0.5, axis=0) - 2.0, np.percentile(allxy, 99.5, axis=0) + 2.0
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal", adjustable="datalim")  # the box fills its room: nothing drawn past the canvas edge
        ax.grid(True, lw=0.3, color="0.85", zorder=0)
        ax.set_xlabel("x (m, from the centre scanner)")
        ax.set_ylabel("y (m)")
        ax.tick_params(labelsize=8)
        if title:
            ax.set_title(title, fontsize=9, wrap=True)
        # the legend goes below the map: over it, it hid trunk shadows
        self.figure.legend(handles=handles, loc="outside lower center", ncols=1, fontsize=7, frameon=False)
        for name, problem in view.problems.items():
            ax.text(0.01, 0.01, f"{name}: {problem}", transform=ax.transAxes, fontsize=7, color="#b42318")
        self.canvas.draw_idle()
