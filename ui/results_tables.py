"""Result tables: one row per link (the registration's evidence) and one per scan (its pose).

Values come from each link's last run (:func:`~forestreg.app.plot.link_summary`), the survey's
figures (:func:`~forestreg.app.plot.scan_quality`, :func:`~forestreg.app.plot.dropped_links`,
:func:`~forestreg.app.plot.pose_sigmas`) and :meth:`Project.poses`; each cell keeps the raw value under ``Qt.UserRole`` so
tests and copy-paste see the numbers, not only their formatting.
"""

from __future__ import annotations

import math
from typing import Any, Optional, Sequence

from PySide6.QtCore import Qt
from PySide6.QtGui import QBrush, QColor
from PySide6.QtWidgets import QAbstractItemView, QHeaderView, QTableWidget, QTableWidgetItem, QWidget

from ..app.plot import Link, PoseSigma, Project, ScanQuality, link_summary, pose_sigmas, scan_quality
from ..app.plot import dropped_links as survey_dropped
from ..engine.report.views import scan_states
from .panes import CellsByName
from .project_model import STATUS_COLOURS, link_status

LINK_COLUMNS = (
    "Moving",
    "Reference",
    "Method",
    "Status",
    "Search radius (m)",
    "Trunk shadows ref / mov",
    "Matched",
    "Fine fit std (cm)",
    "Overlap",
    "Shadow residual (cm)",
    "Pose uncertainty (cm / deg)",
    "Weak motion / alternative",
    "Terrain agreement (cm)",
    "Ambiguity",
    "Dropped",
    "Reason",
)
SCAN_COLUMNS = (
    "Scan",
    "State",
    "Placed on",
    "x (m)",
    "y (m)",
    "z (m)",
    "Heading (\u00b0)",
    "Pose uncertainty (cm / deg)",
    "Terrain agreement (cm)",
    "Ambiguity",
    "Loop residual (cm)",
    "Dropped",
    "Reason",
)
#: Survey quality columns: hidden while no row has a value (a project registered before them).
QUALITY_COLUMNS = (
    "Pose uncertainty (cm / deg)",
    "Terrain agreement (cm)",
    "Ambiguity",
    "Loop residual (cm)",
    "Dropped",
)

LINK_TIPS = {
    "Search radius (m)": "Radius around the scanner in which trunk shadows were extracted (paper: D_r)",
    "Trunk shadows ref / mov": "Trunk shadows (the paper's visual occlusion points, VOPs) found in the reference and the moving scan",
    "Matched": "Trunk shadows of the moving scan that coincide with a reference one after the coarse registration",
    "Fine fit std (cm)": "Standard deviation of the point distances after the fine registration (ICP)",
    "Overlap": "Fraction of moving points in the shared area with a reference point near them after the fine registration (ICP fitness)",
    "Shadow residual (cm)": "Mean distance of the matched trunk shadows (VOPs) after the coarse registration",
    "Pose uncertainty (cm / deg)": "How far to trust the pose, without ground truth (1 sigma): position error at the scanner "
    "in cm and rotation error in degrees. For a link: from its matched trunks after the fine "
    "registration; for a scan: propagated from the centre scan along the most certain links",
    "Weak motion / alternative": "What the stated uncertainty counted beyond the fit: a motion the surfaces hardly pin "
    "(walls or a row along it, a lone trunk) and a distinct solution that fitted nearly as "
    "well (counted in the uncertainty, or excluded with the reason). The full text is in the "
    "cell's tooltip",
    "Terrain agreement (cm)": "Median height difference of the two scans' ground models where both saw the ground, after "
    "registration (for a scan: the worst of its links). Small = the scans agree on the terrain",
    "Ambiguity": "Trunks matched by the second-best coarse solution divided by those of the best (paper: I_A): near 0 = "
    "unambiguous, near 1 = two placements explain the trunks almost equally well (for a scan: its worst link)",
    "Loop residual (cm)": "Largest disagreement, at the scanner, between this scan's links and the adjusted poses "
    "(only where links close loops)",
    "Dropped": "Links the survey adjustment left out because they disagree with the priors or with the other links' loops "
    "(the reason is in the cell's tooltip); for a scan: how many of its links were dropped",
}


def _num(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _item(value: Any, text: Optional[str] = None, *, tip: str = "") -> QTableWidgetItem:
    item = QTableWidgetItem("\u2013" if value is None and text is None else (text if text is not None else str(value)))
    item.setData(Qt.ItemDataRole.UserRole, value)
    item.setFlags(Qt.ItemFlag.ItemIsEnabled | Qt.ItemFlag.ItemIsSelectable)
    if _num(value):
        item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
    if tip:
        item.setToolTip(tip)
    return item


def _fmt(value: Any, digits: int, scale: float = 1.0) -> Optional[str]:
    return f"{value * scale:.{digits}f}" if _num(value) else None


DROPPED_COLOUR = "#b42318"


def dropped_links(project: Project) -> dict[tuple[str, str], str]:
    """The links the survey adjustment dropped, ``(moving, reference) -> reason`` (empty without one)."""
    return {(d.moving, d.reference): d.reason for d in survey_dropped(project)}


def _uncertainty_item(u: Optional[PoseSigma]) -> QTableWidgetItem:
    """The 1-sigma position / rotation error as "1.23 / 0.045" (cm / deg); the raw pair as the value."""
    if u is None or not u.known:
        return _item(None, tip=u.method if u is not None else "")
    t, r = u.translation_m, u.rotation_deg
    item = _item((t, r), f"{100 * t:.2f} / {r:.3f}", tip="held fixed" if u.fixed else u.method)
    item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
    return item


def _notes_item(u: Optional[PoseSigma]) -> QTableWidgetItem:
    """The uncertainty's weak motions and alternatives, shortened in the cell, whole in the tooltip."""
    notes = u.notes if u is not None else ()
    if not notes:
        return _item("", "")
    short = []
    for note in notes:
        if note.startswith("translation along"):
            short.append("free " + note.split(" weakly")[0])
        elif note.startswith("rotation about"):
            short.append("free " + note.split(" weakly")[0])
        elif note.startswith("a distinct solution"):
            where = note[len("a distinct solution ") :].split(" away")[0]
            verdict = "counted" if "is counted" in note else ("same pose" if "same pose" in note else "excluded")
            short.append(f"alternative {where} ({verdict})")
    return _item("; ".join(notes), "; ".join(short), tip="\n".join(notes))


def _figure_item(run: Any, name: str, digits: int, scale: float = 1.0) -> QTableWidgetItem:
    """A figure of a link's last run (an attribute of its :class:`~forestreg.app.plot.LinkSummary`)."""
    value = getattr(run, name) if run is not None else None
    return _item(value, _fmt(value, digits, scale))


def _link_ambiguity(link: Link) -> Optional[float]:
    run = link_summary(link)
    return run.ambiguity if run is not None else None


class _Table(CellsByName, QTableWidget):
    def __init__(self, columns: Sequence[str], parent: Optional[QWidget] = None) -> None:
        super().__init__(0, len(columns), parent)
        self.columns = tuple(columns)
        self.setHorizontalHeaderLabels(list(columns))
        self.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.setAlternatingRowColors(True)
        self.verticalHeader().setVisible(False)
        header = self.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        header.setStretchLastSection(True)
        for k, name in enumerate(columns):
            if name in LINK_TIPS:
                self.horizontalHeaderItem(k).setToolTip(LINK_TIPS[name])

    def column(self, name: str) -> int:  # type: ignore[override]
        """The index of a column by its header."""
        return self.columns.index(name)

    def _hide_empty_reason(self) -> None:
        """No empty "Reason" column taking the room of the figures: shown only when a row has one;
        the survey quality columns likewise only when a row has a value."""
        for name in QUALITY_COLUMNS:
            if name in self.columns:
                c = self.column(name)
                self.setColumnHidden(c, all(self.value(r, name) is None for r in range(self.rowCount())))
        if "Reason" not in self.columns:
            return
        c = self.column("Reason")
        empty = all(not (self.item(r, c) and self.item(r, c).text().strip()) for r in range(self.rowCount()))
        self.setColumnHidden(c, empty)
        self.horizontalHeader().setStretchLastSection(not empty)


class LinkResultsTable(_Table):
    """One row per link of the project: status, D_r, VOPs, matched, ICP std, fitness, reason."""

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(LINK_COLUMNS, parent)

    def show_project(self, project: Project) -> None:
        self.setRowCount(0)
        self.setRowCount(len(project.links))
        dropped = dropped_links(project)
        for r, link in enumerate(project.links):
            run = link_summary(link)
            drop_reason = dropped.get((link.moving, link.reference))
            status = link_status(link)
            reason = run.reason if run is not None else ""
            if run is not None and run.retried:
                reason = (reason + "; " if reason else "") + f"placed after {run.retried} failed attempt(s)"
            vops = (run.reference_vops, run.moving_vops) if run is not None else (None, None)
            cells = [
                _item(link.moving),
                _item(link.reference),
                _item(link.method + (" (extra)" if link.extra else "")),
                _item(status),
                _figure_item(run, "vop_radius_m", 0),
                _item(vops, f"{vops[0]} / {vops[1]}" if None not in vops else "\u2013"),
                _item(
                    run.matched if run is not None else None,
                    None if run is not None and run.matched is not None else "\u2013",
                ),
                _figure_item(run, "icp_std_m", 2, 100.0),
                _figure_item(run, "icp_fitness", 3),
                _figure_item(run, "vop_residual_m", 2, 100.0),
                _uncertainty_item(run.uncertainty if run is not None else None),
                _notes_item(run.uncertainty if run is not None else None),
                _figure_item(run, "terrain_median_m", 1, 100.0),
                _figure_item(run, "ambiguity", 2),
                _item(drop_reason, "dropped" if drop_reason is not None else "", tip=drop_reason or ""),
                _item(reason, reason, tip=reason),
            ]
            colour = STATUS_COLOURS.get(status)
            if colour:
                cells[3].setForeground(QBrush(QColor(colour)))
            if drop_reason is not None:
                cells[self.column("Dropped")].setForeground(QBrush(QColor(DROPPED_COLOUR)))
            for c, cell in enumerate(cells):
                self.setItem(r, c, cell)
        self._hide_empty_reason()


class ScanPoseTable(_Table):
    """One row per scan: its state, the scan it was placed on, and its pose in the project frame
    (translation of its file origin and heading about the vertical)."""

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(SCAN_COLUMNS, parent)

    def show_project(self, project: Project) -> None:
        self.setRowCount(0)
        self.setRowCount(len(project.scans))
        states = scan_states(project) if project.scans else {}
        poses = project.poses() if project.scans else {}
        uncertainty = pose_sigmas(project)
        quality = scan_quality(project)
        dropped = dropped_links(project)
        for r, s in enumerate(project.scans):
            state = states.get(s.name)
            pose = poses.get(s.name)
            status = state.status if state else ""
            link = project.link_of(s.name)
            if status == "failed" and (link is None or link.result is None):
                status = "not run"
            t = pose[:3, 3] if pose is not None else (None, None, None)
            heading = math.degrees(math.atan2(pose[1, 0], pose[0, 0])) if pose is not None else None
            reason = state.reason if state is not None and status == "failed" else ""
            q = quality.get(s.name) or ScanQuality()
            ambiguity = q.max_ambiguity
            if ambiguity is None and link is not None and link.ok:  # no survey: the scan's own link
                ambiguity = _link_ambiguity(link)
            drop_tip = "; ".join(f"{m} \u2192 {ref}: {why}" for (m, ref), why in dropped.items() if s.name in (m, ref))
            cells = [
                _item(s.name),
                _item(status),
                _item(state.reference if state else None, (state.reference or "") if state else ""),
                *(_item(None if v is None else float(v), _fmt(v, 3)) for v in t),
                _item(heading, _fmt(heading, 2)),
                _uncertainty_item(uncertainty.get(s.name) if pose is not None else None),
                _item(q.terrain_median_m, _fmt(q.terrain_median_m, 1, 100.0)),
                _item(ambiguity, _fmt(ambiguity, 2)),
                _item(q.max_residual_m, _fmt(q.max_residual_m, 2, 100.0)),
                _item(q.dropped_links, None if q.dropped_links is not None else "", tip=drop_tip),
                _item(reason, reason, tip=reason),
            ]
            colour = STATUS_COLOURS.get(status)
            if colour:
                cells[1].setForeground(QBrush(QColor(colour)))
            if q.dropped_links:
                cells[self.column("Dropped")].setForeground(QBrush(QColor(DROPPED_COLOUR)))
            for c, cell in enumerate(cells):
                self.setItem(r, c, cell)
        self._hide_empty_reason()
