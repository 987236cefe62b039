"""The 2D top view: each scan's slice, its trunk shadows (VOPs), the scanners and the matched VOP
pairs, in the project frame, from the engine's :func:`compute_top_view` (nothing is recomputed
here; this only draws). With the project, the survey quality goes on the map too: each scanner's
pose uncertainty (a circle, enlarged by a stated factor, and a label in cm / deg), the links
between scanners and the links the survey adjustment dropped (red, dashed). Zoom and pan with the
matplotlib toolbar.

The widget also keeps *marks*: the suggested next scans of a plan (numbered yellow stars) and,
while a plot folder is watched, where each scan that did not link should be taken again (an orange
diamond labelled with the scan's name). They are state of the widget, not of one drawing: every
redraw draws them again, until a new plan or advice replaces them or :meth:`TopViewWidget.clear_marks`
(another project shown)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg, NavigationToolbar2QT
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle
from PySide6.QtWidgets import QSizePolicy, QVBoxLayout, QWidget

from ..app.plot import PoseSigma, Project, dropped_links, pose_sigmas
from ..engine.report.views import TopView

MATCH_COLOUR = "#2ca02c"
LINK_COLOUR = "0.45"
DROPPED_COLOUR = "#b42318"
UNCERTAINTY_COLOUR = "#6a3d9a"
#: The largest uncertainty circle is drawn about this big (m) on the map: the factor is a power of 10.
UNCERTAINTY_DRAWN_M = 3.0
PLAN_FILL, PLAN_LABEL_FILL = "#ffd92f", "#fff7bc"
ADVICE_COLOUR, ADVICE_FILL = "#b35806", "#fdb863"


@dataclass
class SurveyOverlay:
    """What the map shows of the survey quality, straight from the engine: per scan the pose
    uncertainty (``translation_m``, ``rotation_deg``, 1 sigma, relative to the centre scan), the
    successful links kept by the adjustment and the dropped ones with their reasons."""

    uncertainty: dict[str, PoseSigma] = field(default_factory=dict)
    links: list[tuple[str, str]] = field(default_factory=list)
    dropped: dict[tuple[str, str], str] = field(default_factory=dict)

    @classmethod
    def of(cls, project: Project) -> "SurveyOverlay":
        dropped = {(d.moving, d.reference): d.reason for d in dropped_links(project)}
        links = [(x.moving, x.reference) for x in project.links if x.ok and (x.moving, x.reference) not in dropped]
        return cls({k: u for k, u in pose_sigmas(project).items() if u is not None}, links, dropped)


def uncertainty_scale(uncertainty: Mapping[str, PoseSigma]) -> float:
    """The factor (1, 2 or 5 times a power of 10, >= 1) the uncertainty circles are drawn enlarged
    by, so the largest is at most :data:`UNCERTAINTY_DRAWN_M` on the map."""
    largest = max(
        (u.translation_m for u in uncertainty.values() if u.translation_m is not None and u.translation_m > 0),
        default=0.0,
    )
    if largest <= 0 or largest >= UNCERTAINTY_DRAWN_M:
        return 1.0
    wanted = UNCERTAINTY_DRAWN_M / largest
    power = 10.0 ** math.floor(math.log10(wanted))
    return float(max(m * power for m in (1.0, 2.0, 5.0) if m * power <= wanted))


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
        self.overlay: Optional[SurveyOverlay] = None
        #: per scan, the uncertainty label drawn at its scanner (for tests and the screenshot check)
        self.uncertainty_labels: dict[str, str] = {}
        self.uncertainty_factor = 1.0
        #: the suggested next scans marked (:class:`~forestreg.engine.tls.plan.Suggestion`, best first)
        self.plan: tuple = ()
        #: scan that did not link -> the position (x, y, project frame, m) where a scan would link
        self.advice: dict[str, tuple[float, float]] = {}
        #: the marks on the map now: label -> position drawn (x, y, m from the centre scanner)
        self.mark_labels: dict[str, tuple[float, float]] = {}
        self.plan_markers = 0
        self._drawn: Optional[tuple] = None
        self.show_message("Run the registration to see the slices, trunk shadows (VOPs) and matches.")

    @property
    def has_marks(self) -> bool:
        """Whether a plan or a watcher's advice is to be marked on the map."""
        return bool(self.plan or self.advice)

    def set_plan(self, suggestions) -> int:
        """Mark the suggestions of a new plan (replacing the earlier plan's; empty: none) and
        redraw; returns the markers drawn (none while no view is drawn: they are drawn with it)."""
        self.plan = tuple(suggestions)
        self._redraw()
        return self.plan_markers

    def set_advice(self, name: str, position: Optional[tuple]) -> None:
        """Mark where the scan ``name``, which did not link, should be taken again (``position``
        (x, y) in the project frame, m; None: no mark for it, e.g. once it is placed) and redraw."""
        if position is None:
            if self.advice.pop(name, None) is None:
                return
        else:
            self.advice[name] = (float(position[0]), float(position[1]))
        self._redraw()

    def clear_marks(self) -> None:
        """Forget the plan and the advice (another project is shown)."""
        if not self.has_marks:
            return
        self.plan, self.advice = (), {}
        self._redraw()

    def _redraw(self) -> None:
        """Draw the view shown again with the marks as they are now, keeping the zoom when every
        mark lies within it."""
        if self.view is None or self._drawn is None:
            self.plan_markers, self.mark_labels = 0, {}
            return
        ax = self.figure.axes[0] if self.figure.axes else None
        limits = (ax.get_xlim(), ax.get_ylim()) if ax is not None else None
        self.show_view(*self._drawn)
        if limits is None or not self.mark_labels:
            return
        (x0, x1), (y0, y1) = limits
        if all(x0 <= x <= x1 and y0 <= y <= y1 for x, y in self.mark_labels.values()):
            ax = self.figure.axes[0]
            ax.set_xlim(x0, x1)
            ax.set_ylim(y0, y1)
            self.canvas.draw_idle()

    def show_message(self, text: str) -> None:
        """An empty view with a sentence in it."""
        self.view = None
        self._drawn = None
        self.plan_markers, self.mark_labels = 0, {}
        self.figure.clear()
        ax = self.figure.add_subplot()
        ax.set_axis_off()
        ax.text(0.5, 0.5, text, ha="center", va="center", wrap=True, fontsize=11, color="0.35", transform=ax.transAxes)
        self.canvas.draw_idle()

    def show_view(
        self, view: TopView, colours: Mapping[str, str], title: str = "", overlay: Optional[SurveyOverlay] = None
    ) -> None:
        """Draw slices, VOPs (circles), VOP radius, scanners (triangles) and matched pairs (green);
        with ``overlay`` the links between scanners (grey; dropped ones red dashed) and each
        scanner's pose uncertainty (circle and label); and the marks (:meth:`set_plan`,
        :meth:`set_advice`)."""
        self.view = view
        self.overlay = overlay
        self._drawn = (view, colours, title, overlay)
        self.uncertainty_labels = {}
        self.plan_markers, self.mark_labels = 0, {}
        self.figure.clear()
        ax = self.figure.add_subplot()
        if not view.scans:
            ax.set_axis_off()
            ax.text(
                0.5,
                0.5,
                "No registered scan to draw yet.",
                ha="center",
                va="center",
                transform=ax.transAxes,
                color="0.35",
            )
            self.canvas.draw_idle()
            return
        o = view.origin[:2]
        drawn = sum(len(sv.slice_xy) for sv in view.scans.values())
        size = float(np.clip(40000.0 / max(drawn, 1), 0.5, 4.0))
        handles = []
        for name, sv in view.scans.items():
            colour = colours.get(name, "#555555")
            xy = sv.slice_xy - o
            ax.scatter(
                xy[:, 0],
                xy[:, 1],
                s=size,
                color=_lighter(colour, 0.25),
                alpha=0.6,
                linewidths=0,
                rasterized=True,
                zorder=1,
            )
            v = sv.vops_xy - o
            ax.scatter(v[:, 0], v[:, 1], s=26, facecolors="none", edgecolors=colour, linewidths=1.1, zorder=3)
            c = sv.scanner[:2] - o
            ax.add_patch(
                Circle(tuple(c), sv.radius_m, fill=False, ls=(0, (4, 4)), color=colour, lw=0.7, alpha=0.6, zorder=2)
            )
            ax.plot(c[0], c[1], marker="^", ms=11, mfc=colour, mec="k", mew=1.0, ls="none", zorder=6)
            ax.annotate(
                name,
                xy=(c[0], c[1]),
                xytext=(7, 7),
                textcoords="offset points",
                fontsize=8,
                zorder=7,
                bbox=dict(boxstyle="round,pad=0.2", fc="white", ec=colour, lw=1.0, alpha=0.85),
            )
            handles.append(
                Line2D(
                    [],
                    [],
                    ls="none",
                    marker="o",
                    ms=6,
                    mfc="none",
                    mec=colour,
                    mew=1.4,
                    label=f"{name}: {len(sv.vops_xy)} trunk shadows (within {sv.radius_m:.0f} m)",
                )
            )
        n_pairs = 0
        for lv in view.links:
            if not len(lv.pairs):
                continue
            n_pairs += len(lv.pairs)
            a, b = lv.pairs[:, 0] - o, lv.pairs[:, 1] - o
            mid = (a + b) / 2
            ax.scatter(mid[:, 0], mid[:, 1], s=90, facecolors="none", edgecolors=MATCH_COLOUR, linewidths=1.6, zorder=4)
        handles.append(
            Line2D(
                [],
                [],
                ls="none",
                marker="o",
                ms=9,
                mfc="none",
                mec=MATCH_COLOUR,
                mew=1.6,
                label=f"matched trunk shadows ({n_pairs})",
            )
        )
        if overlay is not None:
            handles += self._draw_overlay(ax, view, overlay, o)
        handles += self._draw_marks(ax, o)
        marks = np.array(list(self.mark_labels.values()), dtype=np.float64).reshape(-1, 2)
        allxy = (
            np.concatenate(
                [sv.slice_xy for sv in view.scans.values()] + [sv.scanner[None, :2] for sv in view.scans.values()]
            )
            - o
        )
        if len(allxy):
            lo, hi = np.percentile(allxy, 0.5, axis=0) - 2.0, np.percentile(allxy, 99.5, axis=0) + 2.0
            if len(marks):  # every mark on the map, with room for its label
                lo, hi = np.minimum(lo, marks.min(axis=0) - 3.0), np.maximum(hi, marks.max(axis=0) + 3.0)
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

    def _draw_marks(self, ax, o: np.ndarray) -> list:
        """The plan's suggestions (a numbered star each, labelled with the scan it links to) and
        the watcher's advice (an orange diamond labelled with the scan that did not link); their
        legend entries."""
        handles = []
        for k, s in enumerate(self.plan, 1):
            x, y = s.x - o[0], s.y - o[1]
            ax.plot(x, y, marker="*", ms=22, mfc=PLAN_FILL, mec="k", mew=1.0, ls="none", zorder=8)
            ax.text(x, y, str(k), ha="center", va="center", fontsize=7, fontweight="bold", zorder=9)
            label = f"next {k}: links to {s.links_to}"
            ax.annotate(
                label,
                xy=(x, y),
                xytext=(10, -14),
                textcoords="offset points",
                fontsize=8,
                zorder=9,
                bbox=dict(boxstyle="round,pad=0.2", fc=PLAN_LABEL_FILL, ec="k", lw=0.8, alpha=0.9),
            )
            self.mark_labels[label] = (x, y)
        self.plan_markers = len(self.plan)
        if self.plan:
            handles.append(
                Line2D(
                    [],
                    [],
                    ls="none",
                    marker="*",
                    ms=12,
                    mfc=PLAN_FILL,
                    mec="k",
                    label=f"suggested next scan{'s' if len(self.plan) > 1 else ''}, numbered by what each adds",
                )
            )
        for name, (px, py) in self.advice.items():
            x, y = px - o[0], py - o[1]
            ax.plot(x, y, marker="D", ms=11, mfc=ADVICE_FILL, mec=ADVICE_COLOUR, mew=1.6, ls="none", zorder=8)
            label = f"{name}: not linked, scan again here"
            ax.annotate(
                label,
                xy=(x, y),
                xytext=(9, 8),
                textcoords="offset points",
                fontsize=8,
                zorder=9,
                color=ADVICE_COLOUR,
                bbox=dict(boxstyle="round,pad=0.2", fc="white", ec=ADVICE_COLOUR, lw=1.0, alpha=0.9),
            )
            self.mark_labels[label] = (x, y)
        if self.advice:
            handles.append(
                Line2D(
                    [],
                    [],
                    ls="none",
                    marker="D",
                    ms=8,
                    mfc=ADVICE_FILL,
                    mec=ADVICE_COLOUR,
                    mew=1.4,
                    label="where a scan that did not link would link (the watcher's suggestion)",
                )
            )
        return handles

    def _draw_overlay(self, ax, view: TopView, overlay: SurveyOverlay, o: np.ndarray) -> list:
        """Links between scanners, dropped links and the pose uncertainty at each scanner."""
        handles = []
        where = {name: sv.scanner[:2] - o for name, sv in view.scans.items()}

        def segment(a: str, b: str, **style: Any) -> bool:
            if a not in where or b not in where:
                return False
            (x0, y0), (x1, y1) = where[a], where[b]
            ax.plot([x0, x1], [y0, y1], **style)
            return True

        if sum(segment(m, r, color=LINK_COLOUR, lw=1.0, alpha=0.8, zorder=5) for m, r in overlay.links):
            handles.append(Line2D([], [], color=LINK_COLOUR, lw=1.0, label="link used for the poses"))
        n_dropped = 0
        for (m, r), why in overlay.dropped.items():
            if segment(m, r, color=DROPPED_COLOUR, lw=1.8, ls=(0, (5, 3)), zorder=5):
                n_dropped += 1
                mid = (where[m] + where[r]) / 2
                ax.annotate(
                    "dropped",
                    xy=tuple(mid),
                    xytext=(6, 0),
                    textcoords="offset points",
                    fontsize=7,
                    color=DROPPED_COLOUR,
                    zorder=7,
                    bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8),
                )
        if n_dropped:
            handles.append(
                Line2D(
                    [],
                    [],
                    color=DROPPED_COLOUR,
                    lw=1.8,
                    ls=(0, (5, 3)),
                    label=f"dropped link ({n_dropped}): disagrees with the other links",
                )
            )
        factor = uncertainty_scale(overlay.uncertainty)
        self.uncertainty_factor = factor
        drawn = 0
        for name, u in overlay.uncertainty.items():
            t, r = u.translation_m, u.rotation_deg
            if name not in where or not u.known:
                continue
            c = where[name]
            if u.fixed or (t == 0 and r == 0):
                text = "held fixed" if u.fixed else "frame scan"
            else:
                text = f"\u00b1{100 * t:.1f} cm, {r:.2f}\u00b0"
                ax.add_patch(
                    Circle(
                        tuple(c),
                        t * factor,
                        fill=True,
                        fc=UNCERTAINTY_COLOUR,
                        alpha=0.18,
                        ec=UNCERTAINTY_COLOUR,
                        lw=1.2,
                        zorder=5,
                    )
                )
                drawn += 1
            self.uncertainty_labels[name] = text
            ax.annotate(
                text,
                xy=tuple(c),
                xytext=(7, -16),
                textcoords="offset points",
                fontsize=7,
                color=UNCERTAINTY_COLOUR,
                zorder=7,
                bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8),
            )
        if drawn:
            handles.append(
                Line2D(
                    [],
                    [],
                    ls="none",
                    marker="o",
                    ms=9,
                    mfc=(0.42, 0.24, 0.6, 0.18),
                    mec=UNCERTAINTY_COLOUR,
                    label=f"pose uncertainty, 1 sigma (circle drawn {factor:g}x larger)",
                )
            )
        return handles


def draw_plan(widget: TopViewWidget, suggestions) -> int:
    """Mark suggested next scanner positions (:class:`~forestreg.engine.tls.plan.Suggestion`, in
    the project frame) on the top view: a numbered star each, labelled with the scan it links to,
    kept through every redraw until the next plan (:meth:`TopViewWidget.set_plan`). Returns the
    markers drawn (none while no view is drawn)."""
    return widget.set_plan(suggestions)
