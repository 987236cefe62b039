"""The project tree: a thin Qt item model over :class:`forestreg.engine.tls.project.Project`.

The tree has three groups: *Scans* (the centre scan marked with a star, tilted scans marked, each
with its registration state), *Links* (moving -> reference with the result) and *Tilted pairs*.
Edits (mark centre, mark tilted, link, add or remove scans) go through this model, which changes
the project and emits :attr:`ProjectModel.projectChanged`. Dragging a scan onto another links it
(moving = the dragged scan, reference = the drop target).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Optional, Sequence

from PySide6.QtCore import QByteArray, QMimeData, QModelIndex, QObject, Qt, QTimer, Signal
from PySide6.QtGui import QBrush, QColor, QFont, QStandardItem, QStandardItemModel

from ..app.plot import Link, Project, dropped_links, link_summary
from ..engine.report.views import scan_colours, scan_states

#: Item data roles.
KIND_ROLE = Qt.ItemDataRole.UserRole + 1  # "group", "scan", "link", "pair"
NAME_ROLE = Qt.ItemDataRole.UserRole + 2  # scan name (scan, pair) or link index (link)
#: MIME type of a dragged scan (its name, UTF-8).
SCAN_MIME = "application/x-forestreg-scan"

STATUS_COLOURS = {
    "ok": "#1a7f37",
    "registered": "#1a7f37",
    "centre": "#0b5cad",
    "failed": "#b42318",
    "not run": "#6e6e6e",
    "file missing": "#b42318",
}


def link_status(link: Link) -> str:
    """ "ok", "failed" or "not run"."""
    if link.result is None:
        return "not run"
    return "ok" if link.ok else link.result.status


def link_label(link: Link) -> str:
    """``moving -> reference`` (with the method when manual, "extra" for loop links)."""
    text = f"{link.moving} \u2192 {link.reference}"
    if link.method != "auto":
        text += f" ({link.method})"
    if link.extra:
        text += " [extra]"
    return text


class ProjectModel(QStandardItemModel):
    """Two-column tree (name, state) of a project's scans, links and tilted pairs."""

    projectChanged = Signal()  # the project was edited (scans, centre, links, tilted marks)
    projectReplaced = Signal()  # another project was set
    editFailed = Signal(str)
    refreshed = Signal()  # the tree was rebuilt  # an edit made by drag and drop was refused (the reason)

    def __init__(self, project: Optional[Project] = None, parent: Optional[QObject] = None) -> None:
        super().__init__(parent)
        self.project = project or Project()
        self.editable = True
        self.refresh()

    # ------------------------------------------------------------------ building the tree

    def set_project(self, project: Project) -> None:
        """Show another project."""
        self.project = project
        self.refresh()
        self.projectReplaced.emit()

    def refresh(self) -> None:
        """Rebuild the tree from the project (after a run or an edit)."""
        self.clear()
        self.setHorizontalHeaderLabels(["Item", "State"])
        p = self.project
        states = scan_states(p) if p.scans else {}
        colours = scan_colours(p) if p.scans else {}
        scans = self._group(f"Scans ({len(p.scans)})")
        for s in p.scans:
            state = states.get(s.name)
            text = s.name
            if s.name == p.centre:
                text = "\u2605 " + text
            if s.tilted:
                text += "  (tilted)"
            name_item = QStandardItem(text)
            name_item.setData("scan", KIND_ROLE)
            name_item.setData(s.name, NAME_ROLE)
            name_item.setDragEnabled(True)
            name_item.setDropEnabled(True)
            tip = [f"{s.name}", f"file: {s.path}"]
            if s.name == p.centre:
                tip.append("centre scan: the project frame")
                f = QFont()
                f.setBold(True)
                name_item.setFont(f)
            if s.tilted:
                tip.append("tilted" + (f", beside {s.level_partner}" if s.level_partner else ""))
            placing = p.link_of(s.name)
            if placing is not None:
                tip.append(f"linked to {placing.reference}")
            name_item.setToolTip("\n".join(tip))
            if s.name in colours:
                name_item.setData(QColor(colours[s.name]), Qt.ItemDataRole.DecorationRole)
            status = "centre" if state is None and s.name == p.centre else (state.status if state else "")
            link = p.link_of(s.name)
            if state is not None and state.status == "failed" and (link is None or link.result is None):
                status = "not run"
            missing = not Path(s.path).is_file()
            if missing:  # moved or deleted since the project was saved: say so, whatever the run said
                status = "file missing"
            state_item = QStandardItem(status)
            state_item.setData("scan", KIND_ROLE)
            state_item.setData(s.name, NAME_ROLE)
            if missing:
                state_item.setToolTip(f"not found: {s.path} (File > Relink missing scans…)")
            elif state is not None and state.reason:
                state_item.setToolTip(state.reason)
            self._colour(state_item, status)
            scans.appendRow([name_item, state_item])
        links = self._group(f"Links ({len(p.links)})")
        dropped = {(d.moving, d.reference): d.reason for d in dropped_links(p)}
        for k, link in enumerate(p.links):
            status = link_status(link)
            item = QStandardItem(link_label(link))
            item.setData("link", KIND_ROLE)
            item.setData(k, NAME_ROLE)
            run = link_summary(link)
            detail = status
            if run is not None and run.ok:
                detail = f"ok, {'?' if run.matched is None else run.matched} matched"
            state_item = QStandardItem(detail)
            state_item.setData("link", KIND_ROLE)
            state_item.setData(k, NAME_ROLE)
            if run is not None and run.reason:
                state_item.setToolTip(run.reason)
                item.setToolTip(run.reason)
            self._colour(state_item, status)
            if (link.moving, link.reference) in dropped:  # registered, but the survey adjustment left it out
                state_item.setText(detail + ", dropped")
                state_item.setToolTip(f"dropped by the survey adjustment: {dropped[(link.moving, link.reference)]}")
                state_item.setForeground(QBrush(QColor("#b42318")))
            links.appendRow([item, state_item])
        pairs = self._group("Tilted pairs")
        for s in p.scans:
            if not s.tilted:
                continue
            item = QStandardItem(f"{s.name} beside {s.level_partner or '(found by the run)'}")
            item.setData("pair", KIND_ROLE)
            item.setData(s.name, NAME_ROLE)
            pairs.appendRow([item, QStandardItem("")])
        self.refreshed.emit()

    def _group(self, title: str) -> QStandardItem:
        item = QStandardItem(title)
        item.setData("group", KIND_ROLE)
        item.setEditable(False)
        item.setDragEnabled(False)
        item.setDropEnabled(False)
        f = QFont()
        f.setBold(True)
        item.setFont(f)
        blank = QStandardItem("")
        blank.setEditable(False)
        self.appendRow([item, blank])
        return item

    @staticmethod
    def _colour(item: QStandardItem, status: str) -> None:
        if status in STATUS_COLOURS:
            item.setForeground(QBrush(QColor(STATUS_COLOURS[status])))

    def flags(self, index: QModelIndex) -> Qt.ItemFlag:  # noqa: N802 - Qt API
        base = Qt.ItemFlag.ItemIsEnabled | Qt.ItemFlag.ItemIsSelectable
        if index.isValid() and index.data(KIND_ROLE) == "scan" and self.editable:
            return base | Qt.ItemFlag.ItemIsDragEnabled | Qt.ItemFlag.ItemIsDropEnabled
        return base

    # ------------------------------------------------------------------ lookups

    def scan_name(self, index: QModelIndex) -> Optional[str]:
        """The scan an index shows (a scan row or a tilted pair), else None."""
        if index.isValid() and index.data(KIND_ROLE) in ("scan", "pair"):
            return index.data(NAME_ROLE)
        return None

    def link_at(self, index: QModelIndex) -> Optional[Link]:
        """The link an index shows, else None."""
        if index.isValid() and index.data(KIND_ROLE) == "link":
            k = index.data(NAME_ROLE)
            if isinstance(k, int) and 0 <= k < len(self.project.links):
                return self.project.links[k]
        return None

    def index_of_scan(self, name: str) -> QModelIndex:
        """The index of a scan's row in the Scans group (invalid when absent)."""
        group = self.index(0, 0)
        for r in range(self.rowCount(group)):
            idx = self.index(r, 0, group)
            if idx.data(NAME_ROLE) == name:
                return idx
        return QModelIndex()

    # ------------------------------------------------------------------ edits

    def _changed(self) -> None:
        self.project.adjustment = None
        self.refresh()
        self.projectChanged.emit()

    def add_scans(self, paths: Iterable[str | Path]) -> list[str]:
        """Add scan files; returns the names they got."""
        names = [self.project.add_scan(p).name for p in paths]
        if names:
            self._changed()
        return names

    def remove_scan(self, name: str) -> None:
        """Remove a scan and every link naming it (the next scan becomes centre if it was)."""
        self.project.remove_scan(name)
        self._changed()

    def set_centre(self, name: str) -> None:
        """Make a scan the centre (its own placing link goes; the others keep theirs)."""
        self.project.set_centre(name)
        self._changed()

    def set_tilted(self, name: str, tilted: bool, partner: Optional[str] = None) -> None:
        """Mark a scan tilted (beside ``partner``, or let the run find it) or level."""
        entry = self.project.scan(name)
        if partner is not None:
            self.project.scan(partner)
            if partner == name:
                raise ValueError("a tilted scan's level partner must be another scan")
        entry.tilted = bool(tilted)
        entry.level_partner = partner if tilted else None
        if tilted and partner is not None and name != self.project.centre:
            self.project.set_link(name, partner)
        self._changed()

    def link(self, moving: str, reference: str) -> Link:
        """Register ``moving`` onto ``reference`` (replaces the link that placed ``moving``; the
        project's rules: :meth:`~forestreg.engine.tls.project.Project.set_link`)."""
        link = self.project.set_link(moving, reference)
        self._changed()
        return link

    def clear_results(self, names: Optional[Sequence[str]] = None) -> None:
        """Forget the results of the links placing ``names`` (all links when None)."""
        for link in self.project.links:
            if names is None or link.moving in names:
                link.result = None
        self._changed()

    # ------------------------------------------------------------------ drag and drop

    def supportedDropActions(self) -> Qt.DropAction:  # noqa: N802 - Qt API
        return Qt.DropAction.LinkAction | Qt.DropAction.MoveAction | Qt.DropAction.CopyAction

    def supportedDragActions(self) -> Qt.DropAction:  # noqa: N802 - Qt API
        return Qt.DropAction.LinkAction | Qt.DropAction.MoveAction | Qt.DropAction.CopyAction

    def mimeTypes(self) -> list[str]:  # noqa: N802 - Qt API
        return [SCAN_MIME]

    def mimeData(self, indexes: Sequence[QModelIndex]) -> QMimeData:  # noqa: N802 - Qt API
        data = QMimeData()
        names = [self.scan_name(i) for i in indexes if self.scan_name(i)]
        if names:
            data.setData(SCAN_MIME, QByteArray(names[0].encode("utf-8")))
        return data

    def canDropMimeData(
        self, data: QMimeData, action: Qt.DropAction, row: int, column: int, parent: QModelIndex
    ) -> bool:  # noqa: N802
        target = self.scan_name(parent)
        if not self.editable or not data.hasFormat(SCAN_MIME) or target is None:
            return False
        moving = bytes(data.data(SCAN_MIME)).decode("utf-8")
        return moving != target and moving != self.project.centre

    def dropMimeData(self, data: QMimeData, action: Qt.DropAction, row: int, column: int, parent: QModelIndex) -> bool:  # noqa: N802
        if not self.canDropMimeData(data, action, row, column, parent):
            return False
        moving = bytes(data.data(SCAN_MIME)).decode("utf-8")
        reference = self.scan_name(parent)
        # rebuild after the view has finished its drop
        QTimer.singleShot(0, lambda: self._drop_link(moving, reference))
        return False  # nothing to insert or remove: the tree is rebuilt

    def _drop_link(self, moving: str, reference: str) -> None:
        try:
            self.link(moving, reference)
        except (KeyError, ValueError) as exc:
            self.editFailed.emit(str(exc))
