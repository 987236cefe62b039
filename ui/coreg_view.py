"""The co-registration view (System B): the evidence of a ground-based / UAV co-registration (matches,
surface correlation and its margin over the best alternative, residuals, ICP), the engine's figure
(keypoints before and after, matched pairs, a profile of both clouds), accept or reject, and fusion
with the counts removed per source.

A result comes either from a ``forestreg coregister --out DIR`` folder
(:func:`forestreg.app.coregistration.read_coregistration_folder`) or from a run in this window: the
use case :func:`~forestreg.app.coregistration.coregister_clouds` in a worker thread with progress
and Cancel. Nothing is computed here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QBrush, QColor, QPixmap, QResizeEvent
from PySide6.QtWidgets import QHBoxLayout, QLabel, QPushButton, QSizePolicy, QTableWidgetItem, QVBoxLayout, QWidget

from ..app.coregistration import CoregistrationSummary
from ..app.fusion import SourceCounts
from .panes import TaskProgress, figures_table, headline, lay_out_view, two_panes
from .worker import TaskWorker

OK_COLOUR = "#1f7a3f"
BAD_COLOUR = "#b42318"


@dataclass
class CoregistrationShown:
    """What the view shows: the result's summary (:class:`~forestreg.app.coregistration.
    CoregistrationSummary`), the figure (PNG bytes or a file), the two input files (for fusion),
    and the user's decision ("", "accepted", "rejected")."""

    summary: CoregistrationSummary
    png: Optional[bytes] = None
    figure_path: Optional[Path] = None
    ground_file: str = ""
    uav_file: str = ""
    decision: str = ""

    @property
    def ok(self) -> bool:
        return self.summary.ok

    @property
    def matrix(self) -> Optional[np.ndarray]:
        return self.summary.matrix


def _num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def evidence_rows(summary: CoregistrationSummary) -> list[tuple[str, Any, str, str]]:
    """(label, raw value, text, meaning) of each figure of a co-registration summary."""
    rows: list[tuple[str, Any, str, str]] = []
    dash = "\u2013"

    def add(label: str, value: Any, text: Optional[str], meaning: str) -> None:
        rows.append((label, value, text if text is not None else (dash if value is None else str(value)), meaning))

    def shown(value: Any) -> str:
        return dash if value is None else str(value)

    add(
        "Result",
        summary.status,
        summary.status.upper(),
        summary.reason or "the ground-based cloud was placed on the UAV cloud",
    )
    add(
        "Keypoints ground / UAV",
        (summary.keypoints_ground, summary.keypoints_uav),
        f"{shown(summary.keypoints_ground)} / {shown(summary.keypoints_uav)}",
        "tree tops found in each cloud's canopy (paper: canopy keypoints)",
    )
    pct = summary.matching_percentage
    add(
        "Matched keypoints",
        summary.matched,
        shown(summary.matched) + (f"  ({pct:.0f} % of the ground-based)" if _num(pct) else ""),
        "ground-based tree tops that coincide with a UAV tree top after the registration",
    )
    corr, alt, margin = summary.surface_correlation, summary.alternative_correlation, summary.margin
    add(
        "Canopy surface correlation",
        corr,
        f"{corr:.2f}" if _num(corr) else None,
        "how well the two canopy surfaces agree after the registration (1 = identical; right answers 0.8-0.9)",
    )
    add("Best alternative", alt, f"{alt:.2f}" if _num(alt) else None, "correlation of the best distinct other solution")
    add(
        "Margin over the alternative",
        margin,
        f"{margin:.2f}" if margin is not None else None,
        "a large margin means the solution is not a guess between look-alike placements",
    )
    heading = summary.heading_deg
    add(
        "Turn about the vertical",
        heading,
        f"{heading:.2f}\u00b0" if _num(heading) else None,
        "heading of the ground-based cloud in the UAV frame",
    )
    for v, label in (
        (summary.residual_mean_m, "Keypoint residual, mean"),
        (summary.residual_rms_m, "Keypoint residual, RMS"),
    ):
        add(
            label,
            v,
            f"{100 * v:.1f} cm" if _num(v) else None,
            "distance between matched tree tops after the registration",
        )
    f, s = summary.icp_fitness, summary.icp_std_m
    add(
        "Fine fit overlap",
        f,
        f"{f:.2f}" if _num(f) else None,
        "share of points with a partner in the other cloud after ICP",
    )
    add(
        "Fine fit std",
        s,
        f"{100 * s:.1f} cm" if _num(s) else None,
        "standard deviation of the point distances after ICP",
    )
    for key, v in summary.standard_errors.items():
        add(f"Standard error {key}", v, f"{v:.4g}", "uncertainty of the transform estimated by the engine")
    t = summary.total_s
    add("Time", t, f"{t:.0f} s" if _num(t) else None, "engine time")
    return rows


class _Picture(QLabel):
    """A label that keeps its picture scaled to its size."""

    def __init__(self) -> None:
        super().__init__()
        self._pix: Optional[QPixmap] = None
        self.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self.setMinimumSize(200, 150)
        self.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Ignored)
        self.setStyleSheet("background: white;")

    def set_picture(self, pix: Optional[QPixmap], text: str = "") -> None:
        self._pix = pix if pix is not None and not pix.isNull() else None
        if self._pix is None:
            self.setPixmap(QPixmap())
            self.setText(text)
        else:
            self.setText("")
            self._rescale()

    def _rescale(self) -> None:
        if self._pix is not None:
            self.setPixmap(
                self._pix.scaled(
                    self.size(), Qt.AspectRatioMode.KeepAspectRatio, Qt.TransformationMode.SmoothTransformation
                )
            )

    def resizeEvent(self, event: QResizeEvent) -> None:  # noqa: N802 - Qt API
        super().resizeEvent(event)
        self._rescale()


class CoregistrationView(QWidget):
    """Evidence table, the engine's figure, Accept / Reject / Fuse, progress and Cancel."""

    decided = Signal(str)  # "accepted" / "rejected"
    finished = Signal(object)  # CoregistrationShown after a run
    fused = Signal(object)  # the fusion counts

    def __init__(self, start_task: Callable[..., Any], parent: Optional[QWidget] = None) -> None:
        super().__init__(parent)
        self._start_task = start_task
        self.shown: Optional[CoregistrationShown] = None
        self.worker: Optional[TaskWorker] = None
        self.fusion_counts: Optional[dict[str, dict[str, int]]] = None
        self.fused_path: Optional[str] = None
        self.last_error: Optional[tuple[str, str]] = None
        self.headline = headline(
            "Open a co-registration result (File \u25b8 Open co-registration result\u2026) or run one "
            "(Co-register\u2026): the ground-based cloud is placed on the UAV/ALS cloud by tree tops."
        )
        self.run_button = QPushButton("Co-register\u2026")
        self.run_button.setToolTip("Choose a ground-based cloud and a UAV/ALS cloud and co-register them")
        self.accept_button = QPushButton("Accept")
        self.accept_button.setToolTip("Keep this transform for fusion and tree measurement")
        self.reject_button = QPushButton("Reject")
        self.reject_button.setToolTip("Do not use this transform")
        self.fuse_button = QPushButton("Fuse\u2026")
        self.fuse_button.setToolTip("Merge both clouds with the accepted transform, removing duplicates and noise")
        self.task = TaskProgress(self.cancel)
        self.progress, self.cancel_button = self.task.bar, self.task.cancel_button
        self.accept_button.clicked.connect(lambda: self.decide("accepted"))
        self.reject_button.clicked.connect(lambda: self.decide("rejected"))
        bar = QHBoxLayout()
        for w in (self.run_button, self.accept_button, self.reject_button, self.fuse_button):
            bar.addWidget(w)
        bar.addWidget(self.progress, 1)
        bar.addWidget(self.cancel_button)
        bar.addStretch(0)
        self.table = figures_table(["Evidence", "Value", "What it means"])
        self.table.setWordWrap(False)
        self.fusion_label = QLabel("")
        self.fusion_label.setWordWrap(True)
        left = QWidget()
        ll = QVBoxLayout(left)
        ll.setContentsMargins(0, 0, 0, 0)
        ll.addWidget(self.table, 1)
        ll.addWidget(self.fusion_label)
        self.picture = _Picture()
        lay_out_view(
            self, self.headline, two_panes(Qt.Orientation.Vertical, self.picture, left, (420, 300)), rows=[bar]
        )
        self._update_buttons()

    # ------------------------------------------------------------------ showing

    def show_result(self, shown: CoregistrationShown) -> None:
        self.shown = shown
        self.fusion_counts = None
        self.fusion_label.setText("")
        s = shown.summary
        if shown.ok:
            self.headline.setText(
                f"<b style='color:{OK_COLOUR}'>Co-registered</b>: {s.ground or 'ground'} \u2192 "
                f"{s.uav or 'uav'}. Check the figure (matched tree tops joined by black lines, "
                "the profile on the right), then accept or reject."
            )
        else:
            self.headline.setText(
                f"<b style='color:{BAD_COLOUR}'>Not co-registered</b>: {s.reason or 'no reason given'}"
            )
        rows = evidence_rows(s)
        self.table.setRowCount(len(rows))
        for r, (label, value, text, meaning) in enumerate(rows):
            a = QTableWidgetItem(label)
            a.setToolTip(meaning)
            b = QTableWidgetItem(text)
            b.setData(Qt.ItemDataRole.UserRole, value)
            b.setToolTip(meaning)
            c = QTableWidgetItem(meaning)
            c.setForeground(QBrush(QColor("#475467")))
            self.table.setItem(r, 2, c)
            if r == 0:
                b.setForeground(QBrush(QColor(OK_COLOUR if shown.ok else BAD_COLOUR)))
            self.table.setItem(r, 0, a)
            self.table.setItem(r, 1, b)
        pix = QPixmap()
        if shown.png:
            pix.loadFromData(shown.png)
        elif shown.figure_path is not None:
            pix.load(str(shown.figure_path))
        self.picture.set_picture(pix, "No figure")
        self._update_buttons()

    def value(self, label: str) -> Any:
        """The raw value of an evidence row (tests)."""
        for r in range(self.table.rowCount()):
            if self.table.item(r, 0).text() == label:
                return self.table.item(r, 1).data(Qt.ItemDataRole.UserRole)
        raise KeyError(label)

    def decide(self, decision: str) -> None:
        if self.shown is None:
            return
        if decision == "accepted" and not self.shown.ok:
            return
        self.shown.decision = decision
        note = {"accepted": "accepted: fusion and trees use this transform", "rejected": "rejected: not used"}[decision]
        self.headline.setText(self.headline.text().split("<br>")[0] + f"<br><i>{note}</i>")
        self._update_buttons()
        self.decided.emit(decision)

    def _update_buttons(self) -> None:
        running = self.worker is not None
        ok = self.shown is not None and self.shown.ok
        self.run_button.setEnabled(not running)
        self.accept_button.setEnabled(ok and not running and self.shown.decision != "accepted")
        self.reject_button.setEnabled(self.shown is not None and not running and self.shown.decision != "rejected")
        self.fuse_button.setEnabled(
            ok
            and not running
            and self.shown.decision == "accepted"
            and bool(self.shown.ground_file)
            and bool(self.shown.uav_file)
        )

    # ------------------------------------------------------------------ work

    def _begin(self, worker: TaskWorker, succeeded: Callable[[Any], None], what: str) -> None:
        self.worker = worker
        self.last_error = None
        self.task.begin(what)
        self._update_buttons()

        def failed(message: str, details: str) -> None:
            self.last_error = (message, details)
            self.headline.setText(f"<b style='color:{BAD_COLOUR}'>{what} failed</b>: {message}")

        def cancelled() -> None:
            self.headline.setText(f"{what} cancelled.")

        def ended() -> None:
            self.worker = None
            self.task.end()
            self._update_buttons()

        self._start_task(
            worker, succeeded=succeeded, failed=failed, cancelled=cancelled, progress=self.task.report, ended=ended
        )

    def cancel(self) -> None:
        if self.worker is not None:
            self.worker.cancel()

    def run(self, ground_file: str, uav_file: str) -> None:
        """Co-register two cloud files in a worker (the engine's defaults)."""

        def task(progress: Callable[[float, str], None], cancel: Any) -> CoregistrationShown:
            from ..app.coregistration import coregister_clouds
            from ..engine.io import read_scan
            from ..engine.report.coregistration_report import coregistration_png

            progress(0.0, "reading the clouds")
            ground, uav = read_scan(ground_file), read_scan(uav_file)
            # the same use case as the command line: its last check withholds a matrix that is not rigid
            outcome = coregister_clouds(
                ground, uav, None, progress=lambda f, m: progress(0.05 + 0.85 * f, m), cancel=cancel
            )
            progress(0.92, "drawing the figure")
            result = outcome.result
            png = coregistration_png(result, ground.points, uav.points) if result.ground_keypoints is not None else None
            return CoregistrationShown(
                summary=outcome.figures, png=png, ground_file=str(ground_file), uav_file=str(uav_file)
            )

        def done(shown: CoregistrationShown) -> None:
            self.show_result(shown)
            self.finished.emit(shown)

        self._begin(TaskWorker(task, name="coregistration"), done, "Co-registration")

    def fuse(self, out_file: str) -> None:
        """Fuse the two clouds with the accepted transform into ``out_file`` (LAS/LAZ) in a worker."""
        shown = self.shown
        if shown is None or shown.decision != "accepted" or shown.matrix is None:
            return
        matrix = shown.matrix

        def task(progress: Callable[[float, str], None], cancel: Any) -> dict[str, SourceCounts]:
            from ..app.fusion import fuse_clouds

            progress(0.0, "reading the clouds")
            outcome = fuse_clouds(
                shown.ground_file,
                shown.uav_file,
                out_file,
                matrix=matrix,
                progress=lambda f, m: progress(0.05 + 0.9 * f, m),
                cancel=cancel,
            )
            return outcome.sources

        def done(counts: dict[str, SourceCounts]) -> None:
            self.fusion_counts = counts
            self.fused_path = out_file
            lines = [f"<b>Fused</b> into {out_file}:"]
            for source in ("ground", "uav", "total"):
                c = counts.get(source)
                if c:
                    lines.append(
                        f"{source}: {c.input:,} in, {c.redundant:,} duplicates and {c.noise:,} noise removed, {c.kept:,} kept"
                    )
            self.fusion_label.setText("<br>".join(lines))
            self.fused.emit(counts)

        self._begin(TaskWorker(task, name="fusion"), done, "Fusion")


def shown_from_folder(out: Any, summary: CoregistrationSummary) -> CoregistrationShown:
    """A :class:`CoregistrationShown` of a folder read by
    :func:`~forestreg.app.coregistration.read_coregistration_folder` (its output and summary)."""
    return CoregistrationShown(
        summary=summary, figure_path=out.figure, ground_file=summary.ground_file, uav_file=summary.uav_file
    )
