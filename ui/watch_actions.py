"""Field registration in the desktop: *File > Watch folder...* runs the watcher of
:mod:`forestreg.app.watch` (the one ``forestreg plot --watch FOLDER --out OUT`` runs) as a
background task. Each scan placed appears in the project tree and its link in the links table as
the plot folder is updated; a scan that does not link is listed in the *Watch* tab with the
watcher's reason and the position that would link, and that position is marked on the top view
with the scan's name (until the scan is placed). Cancel stops the watch between two updates of
the plot folder, which stays whole (each update is one transaction).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Optional

from PySide6.QtCore import QObject, Signal, Slot
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (
    QDialog,
    QDialogButtonBox,
    QFileDialog,
    QFormLayout,
    QHBoxLayout,
    QLineEdit,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QWidget,
)

from .worker import TaskWorker

log = logging.getLogger("forestreg")

#: Columns of the Watch tab.
WATCH_COLUMNS = ("Scan", "Status", "Linked to", "Reason / what to do", "Suggested position (x, y m)")
#: Text colour of a scan's status in the Watch tab.
STATUS_COLOURS = {"centre": "#1b7837", "linked": "#1b7837", "not linked": "#b35806", "refused": "#b2182b"}


class WatchWorker(TaskWorker):
    """Runs :func:`~forestreg.app.watch.watch_plot` on ``folder`` into ``out`` until cancelled.

    Extra signal: ``scan_event(WatchEvent)`` for each file the watcher took a decision on (emitted
    in the worker's thread, after the plot folder was updated). Cancelling stops the watch at its
    next poll, or at the engine's next check while a scan is being registered; either way the plot
    folder holds the files of its last update.
    """

    scan_event = Signal(object)

    def __init__(
        self, folder: Path, out: Path, params: Any, *, centre: Optional[str] = None, poll_s: float = 0.5
    ) -> None:
        super().__init__(self._watch, name="watch")
        self.folder, self.out, self.params, self.centre, self.poll_s = Path(folder), Path(out), params, centre, poll_s

    def _sleep(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if self.token.cancelled:
                raise KeyboardInterrupt  # the watcher's own way of stopping: it ends normally
            time.sleep(min(0.05, max(0.0, end - time.monotonic())))
        if self.token.cancelled:
            raise KeyboardInterrupt

    def _watch(self, progress: Any, cancel: Any) -> Any:
        from ..app.watch import watch_plot

        return watch_plot(
            self.folder,
            self.out,
            self.params,
            centre=self.centre,
            poll_s=self.poll_s,
            on_event=self.scan_event.emit,
            progress=progress,
            cancel=cancel,
            sleep=self._sleep,
        )


class _EventRelay(QObject):
    """Receives a watch worker's events in the GUI thread."""

    def __init__(self, parent: QObject, fn: Any) -> None:
        super().__init__(parent)
        self.fn = fn

    @Slot(object)
    def deliver(self, ev: Any) -> None:
        self.fn(ev)


class WatchTable(QTableWidget):
    """The Watch tab: one row per file the watcher decided on, its latest status."""

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(0, len(WATCH_COLUMNS), parent)
        self.setObjectName("watch-table")
        self.setHorizontalHeaderLabels(list(WATCH_COLUMNS))
        self.setEditTriggers(QTableWidget.EditTrigger.NoEditTriggers)
        self.horizontalHeader().setStretchLastSection(False)
        self.verticalHeader().hide()
        self.rows: dict[str, int] = {}

    def clear_rows(self) -> None:
        self.setRowCount(0)
        self.rows.clear()

    def show_event(self, ev: Any) -> None:
        row = self.rows.get(ev.name)
        if row is None:
            row = self.rowCount()
            self.insertRow(row)
            self.rows[ev.name] = row
        reason = ev.reason or ("" if ev.status in ("centre", "linked") else ev.message.split(": ", 1)[-1])
        if ev.status == "not linked" and ev.advice is not None:
            reason = f"{reason}: stand between them, near ({ev.advice[0]:.1f}, {ev.advice[1]:.1f})"
        elif ev.status == "refused":
            reason = f"{reason}: a scan of another plot, or taken too far from every placed scan"
        position = "" if ev.advice is None else f"{ev.advice[0]:.1f}, {ev.advice[1]:.1f}"
        values = (ev.name, ev.status, ev.reference or ev.same_as or "", reason, position)
        for col, text in enumerate(values):
            item = QTableWidgetItem(text)
            item.setToolTip(ev.message)
            if col == 1 and ev.status in STATUS_COLOURS:
                item.setForeground(QColor(STATUS_COLOURS[ev.status]))
            self.setItem(row, col, item)
        self.resizeColumnsToContents()

    def text(self, name: str, column: str) -> str:
        item = self.item(self.rows[name], WATCH_COLUMNS.index(column))
        return "" if item is None else item.text()


class WatchDialog(QDialog):
    """Asks for the watched folder, the plot folder to write and (optionally) the centre scan."""

    def __init__(self, parent: QWidget, start: str) -> None:
        super().__init__(parent)
        self.setWindowTitle("Watch folder")
        form = QFormLayout(self)
        self.folder = self._row(form, "Folder the scanner fills", start, "Folder the scanner's export fills")
        self.out = self._row(
            form, "Plot folder to write", str(Path(start) / "registered"), "Output folder (new, or a watch's to go on)"
        )
        self.centre = QLineEdit()
        self.centre.setPlaceholderText("the first scan to arrive")
        self.centre.setToolTip("File name of the centre scan (the plot's frame); empty: the first scan to arrive")
        form.addRow("Centre scan (optional)", self.centre)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        form.addRow(buttons)

    def _row(self, form: QFormLayout, label: str, value: str, title: str) -> QLineEdit:
        edit = QLineEdit(value)
        browse = QPushButton("Browse\u2026")

        def ask() -> None:
            chosen = QFileDialog.getExistingDirectory(self, title, edit.text())
            if chosen:
                edit.setText(chosen)

        browse.clicked.connect(ask)
        box = QHBoxLayout()
        box.addWidget(edit, 1)
        box.addWidget(browse)
        form.addRow(label, box)
        return edit


class WatchMixin:
    """The window's watch: :meth:`watch_folder` starts it, Cancel (the window's) stops it."""

    def _build_watch(self) -> None:
        self.watch_table = WatchTable()
        self.bottom_tabs.addTab(self.watch_table, "Watch")
        self.watch_worker: Optional[WatchWorker] = None
        self.watch_events: list = []
        self.watch_run: Any = None
        self._watch_relay = _EventRelay(self, self._watch_event)

    def _ask_watch_folder(self) -> None:
        if self.running:
            return
        dialog = WatchDialog(self, self._last_dir())
        if dialog.exec() != QDialog.DialogCode.Accepted:
            return
        folder, out, centre = dialog.folder.text().strip(), dialog.out.text().strip(), dialog.centre.text().strip()
        if folder and out:
            self._remember_dir(folder)
            self.watch_folder(folder, out, centre=centre or None)

    def watch_folder(
        self, folder: str | Path, out: str | Path, *, centre: Optional[str] = None, poll_s: float = 0.5
    ) -> bool:
        """Watch ``folder`` and register each scan arriving there into the plot folder ``out``
        (the parameter panel's settings), showing each as it is placed; False when it cannot start."""
        if self.running or not self.confirm_discard():
            return False
        if not self.apply_panel_params():
            return False
        from ..app.plot import Project

        params = self.project.params
        self.set_project(Project(name=Path(out).name, params=params))
        worker = WatchWorker(Path(folder), Path(out), params, centre=centre, poll_s=poll_s)
        worker.scan_event.connect(self._watch_relay.deliver)
        self.watch_worker = self.run_worker = worker
        self.watch_events, self.watch_run = [], None
        self.watch_table.clear_rows()
        self.last_error = None
        self._set_busy(True, f"Watching {folder}\u2026 (Cancel stops the watch)")
        self.progress_bar.setRange(0, 0)  # no end known: a busy bar
        self.bottom_tabs.setCurrentWidget(self.watch_table)
        log.info("watching %s into %s", folder, out)
        self.tasks.start(
            worker,
            succeeded=self._watch_finished,
            failed=self._watch_failed,
            cancelled=self._watch_cancelled,
            progress=self._watch_progress,
            ended=self._watch_ended,
        )
        return True

    def _watch_progress(self, fraction: float, message: str) -> None:
        if message and self.watch_worker is not None and not self.watch_worker.token.cancelled:
            self.status_label.setText(message)

    def _watch_event(self, ev: Any) -> None:
        self.watch_events.append(ev)
        log.info("%s", ev.message)
        self.watch_table.show_event(ev)
        if ev.status in ("centre", "linked", "not linked", "refused"):
            # marked before the folder is shown: the top view drawn for it has the mark
            self.top_view.set_advice(ev.name, ev.advice if ev.status == "not linked" else None)
            self._show_plot_folder()
        if self.watch_worker is not None and not self.watch_worker.token.cancelled:
            self.status_label.setText(f"Watching: {ev.message}")

    def _show_plot_folder(self) -> None:
        """Show the plot folder's project as the watcher last wrote it."""
        from ..app.plot import Project
        from ..engine.core.errors import ForestregError

        worker = self.watch_worker
        if worker is None or not (worker.out / "project.json").is_file():
            return
        try:
            project = Project.load(worker.out / "project.json")
        except (ForestregError, OSError) as exc:
            log.warning("the plot folder cannot be shown: %s", exc)
            return
        self.set_project(project)
        self.bottom_tabs.setCurrentWidget(self.watch_table)

    def _watch_finished(self, run: Any) -> None:
        self.watch_run = run
        text = f"Watch stopped: {len(run.placed)} scan{'s' if len(run.placed) != 1 else ''} placed"
        if run.aside:
            text += f"; not placed: {', '.join(run.aside)}"
        log.info("%s", text)
        self.status_label.setText(text)

    def _watch_failed(self, message: str, details: str) -> None:
        self.status_label.setText("The watch failed")
        self.show_error("The watch failed", message, details)

    def _watch_cancelled(self) -> None:
        self.status_label.setText("Watch stopped; the plot folder holds its last update")

    def _watch_ended(self) -> None:
        text = self.status_label.text()
        self._show_plot_folder()
        self.watch_worker = None
        self.progress_bar.setRange(0, 1000)
        self._run_ended()
        self.bottom_tabs.setCurrentWidget(self.watch_table)
        self.status_label.setText(text)


class PlanMixin:
    """*Registration > Plan next scan*: :func:`~forestreg.app.plan.plan_project` on the project
    as it is, its suggestions marked on the top view until the next plan or another project."""

    def plan_next_scan(self, n: int = 3) -> bool:
        """Plan the next ``n`` scans in the background and mark them on the map; False when
        nothing is placed yet or a run is going on."""
        if self.running or not any(
            p is not None for name, p in self.project.poses().items() if name != self.project.centre
        ):
            return False
        from ..app.plan import plan_project

        project, scans = self.project, self.scans
        worker = TaskWorker(
            lambda progress, cancel: plan_project(project, n=n, scans=scans, progress=progress)[0], name="plan"
        )
        self.status_label.setText("Planning the next scans\u2026")
        self._start_task(
            worker, succeeded=self._plan_done, failed=lambda m, d: self.show_error("No plan for the next scan", m, d)
        )
        return True

    def _plan_done(self, plan: Any) -> None:
        from .top_view import draw_plan

        self.last_plan = plan
        draw_plan(self.top_view, plan.suggestions)  # replaces the earlier plan's marks, kept through redraws
        if not plan.suggestions:
            self.status_label.setText(f"No next scan suggested: {plan.reason}")
            return
        where = "; ".join(f"({s.x:.1f}, {s.y:.1f}) linking to {s.links_to}" for s in plan.suggestions)
        text = f"Next scan{'s' if len(plan.suggestions) > 1 else ''}: {where}"
        log.info("%s", text)
        self.status_label.setText(text)
