"""The main window of forestreg: project tree, 3D and top views, parameters, results and log.

Everything the window computes goes through the engine in a background thread
(:mod:`forestreg.ui.worker`); the window only shows the project and edits it through
:class:`~forestreg.ui.project_model.ProjectModel`.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Optional

from PySide6.QtCore import QByteArray, QModelIndex, QPoint, QSettings, Qt, QTimer, Signal
from PySide6.QtGui import QAction, QActionGroup, QCloseEvent, QKeySequence
from PySide6.QtWidgets import (
    QAbstractItemView,
    QDockWidget,
    QLabel,
    QMainWindow,
    QMenu,
    QMessageBox,
    QProgressBar,
    QPushButton,
    QSplitter,
    QTabWidget,
    QTreeView,
    QWidget,
)

from ..app.plot import Project, ScanCache
from ..engine.core.errors import ForestregError
from .file_actions import FileActionsMixin
from .icons import icon
from .log_pane import LogPane
from .manual_mode import ManualModeMixin
from .params_panel import ParameterPanel
from .project_model import ProjectModel
from .results_tables import LinkResultsTable, ScanPoseTable
from .scene_data import PreviewCache, build_scene
from .scene_view import SceneView
from .system_b import SystemBMixin
from .tasks import TaskSet
from .top_view import TopViewWidget
from .watch_actions import PlanMixin, WatchMixin
from .worker import RegistrationWorker, TaskWorker

log = logging.getLogger("forestreg")

ORGANISATION = "forestreg"
APPLICATION = "forestreg"


class MainWindow(PlanMixin, WatchMixin, SystemBMixin, ManualModeMixin, FileActionsMixin, QMainWindow):
    """forestreg's main window over one project.

    ``settings``: where recent files and the window layout are kept (default
    ``QSettings("forestreg", "forestreg")``). ``interactive=False`` never opens a blocking
    dialog (offscreen mode, tests): errors go to the log and :attr:`last_error`.
    ``renderer``: the 3D view's renderer, see :func:`forestreg.ui.scene_view.choose_renderer`.
    """

    runFinished = Signal(object)  # PlotOutcome
    runFailed = Signal(str, str)  # message, details
    runCancelled = Signal()
    sceneReady = Signal()
    topViewReady = Signal()
    projectLoaded = Signal()
    # manual mode (forestreg.ui.manual_mode)
    targetsChanged = Signal(str)  # scan name
    reflectorsDetected = Signal(str, int)  # scan name, targets added or renamed
    comparisonReady = Signal(object)  # the comparison dict
    comparisonFailed = Signal(str, str)

    def __init__(
        self,
        *,
        settings: Optional[QSettings] = None,
        interactive: bool = True,
        renderer: Optional[str] = None,
        parent: Optional[QWidget] = None,
    ) -> None:
        super().__init__(parent)
        self.settings = settings if settings is not None else QSettings(ORGANISATION, APPLICATION)
        self.interactive = interactive
        self._renderer = renderer
        self.last_error: Optional[tuple[str, str, str]] = None
        self.dirty = False
        self.scene_mode = "before"
        self.run_worker: Optional[RegistrationWorker] = None
        self.last_outcome: Any = None
        self.tasks = TaskSet(self)
        self._pending: set[str] = set()
        self.model = ProjectModel(Project(name="untitled"), self)
        self.scans = ScanCache(self.model.project)
        self.previews = PreviewCache(self.scans)
        self.setObjectName("forestreg-main")
        self.setDockOptions(QMainWindow.DockOption.AnimatedDocks | QMainWindow.DockOption.AllowNestedDocks)

        self._build_views()
        self._build_watch()
        self._build_actions()
        self._build_menus()
        self._build_status()
        self._build_manual()
        self.model.projectChanged.connect(self._project_edited)
        self.model.editFailed.connect(lambda text: self.show_error("Cannot link", text))
        self.params_panel.paramsChanged.connect(self._params_edited)
        self.params_panel.load_button.clicked.connect(self._ask_load_params)
        self.resize(1600, 1000)
        self._restore_settings()
        self._project_replaced()

    # ================================================================== building

    def _build_views(self) -> None:
        self.scene_view = SceneView(renderer=self._renderer_choice())
        self.top_view = TopViewWidget()
        split = QSplitter(Qt.Orientation.Horizontal)
        split.addWidget(self.scene_view)
        split.addWidget(self.top_view)
        split.setStretchFactor(0, 3)
        split.setStretchFactor(1, 2)
        split.setSizes([620, 420])
        self.view_splitter = split
        self.setCentralWidget(self._build_system_b(split))

        self.tree = QTreeView()
        self.tree.setObjectName("project-tree")
        self.tree.setModel(self.model)
        self.tree.setHeaderHidden(False)
        self.tree.setContextMenuPolicy(Qt.ContextMenuPolicy.CustomContextMenu)
        self.tree.customContextMenuRequested.connect(self._tree_menu)
        self.tree.setDragEnabled(True)
        self.tree.setAcceptDrops(True)
        self.tree.setDropIndicatorShown(True)
        self.tree.setDragDropMode(QAbstractItemView.DragDropMode.DragDrop)
        self.tree.setDefaultDropAction(Qt.DropAction.LinkAction)
        self.tree.setToolTip(
            "Right-click a scan to mark the centre or a tilted scan; drag a scan onto another to link it"
        )
        self.model.refreshed.connect(self._tree_refreshed)
        self.tree_dock = self._dock("Project", self.tree, Qt.DockWidgetArea.LeftDockWidgetArea)

        self.params_panel = ParameterPanel()
        self.params_dock = self._dock("Parameters", self.params_panel, Qt.DockWidgetArea.LeftDockWidgetArea)
        self.splitDockWidget(self.tree_dock, self.params_dock, Qt.Orientation.Vertical)

        self.link_table = LinkResultsTable()
        self.scan_table = ScanPoseTable()
        self.log_pane = LogPane()
        self.bottom_tabs = QTabWidget()
        self.bottom_tabs.addTab(self.link_table, "Links")
        self.bottom_tabs.addTab(self.scan_table, "Scans")
        self.bottom_tabs.addTab(self.log_pane, "Log")
        self.results_dock = self._dock("Results", self.bottom_tabs, Qt.DockWidgetArea.BottomDockWidgetArea)
        self.resizeDocks([self.tree_dock, self.params_dock], [300, 500], Qt.Orientation.Vertical)
        self.resizeDocks([self.tree_dock], [360], Qt.Orientation.Horizontal)
        self.resizeDocks([self.results_dock], [170], Qt.Orientation.Vertical)

    def _tree_refreshed(self) -> None:
        self.tree.expandAll()
        self.tree.resizeColumnToContents(0)

    def _renderer_choice(self) -> Optional[str]:
        return self._renderer

    def _dock(self, title: str, widget: QWidget, area: Qt.DockWidgetArea) -> QDockWidget:
        dock = QDockWidget(title, self)
        dock.setObjectName(f"dock-{title.lower()}")
        dock.setWidget(widget)
        dock.setFeatures(
            QDockWidget.DockWidgetFeature.DockWidgetMovable
            | QDockWidget.DockWidgetFeature.DockWidgetFloatable
            | QDockWidget.DockWidgetFeature.DockWidgetClosable
        )
        self.addDockWidget(area, dock)
        return dock

    def _action(
        self, text: str, slot: Callable[[], Any], shortcut: Any = None, tip: str = "", checkable: bool = False
    ) -> QAction:
        action = QAction(text, self)
        if shortcut is not None:
            action.setShortcut(QKeySequence(shortcut))
        if tip:
            action.setStatusTip(tip)
            action.setToolTip(f"{tip} ({action.shortcut().toString()})" if shortcut is not None else tip)
        action.setCheckable(checkable)
        action.triggered.connect(lambda checked=False: slot())
        return action

    def _build_actions(self) -> None:
        a = self._action
        self.act_new = a("&New project", self.new_project, QKeySequence.StandardKey.New, "Start an empty project")
        self.act_open = a("&Open project\u2026", self._ask_open, QKeySequence.StandardKey.Open, "Open a saved project")
        self.act_sample = a(
            "Open &sample plot",
            self.open_sample,
            None,
            "Open a simulated forest plot with three scans (made on first use)",
        )
        self.act_save = a("&Save project", self._save, QKeySequence.StandardKey.Save, "Save the project")
        self.act_save_as = a(
            "Save project &as\u2026",
            self._ask_save_as,
            QKeySequence("Ctrl+Shift+S"),
            "Save the project to another file",
        )
        self.act_add = a(
            "&Add scans\u2026",
            self._ask_add_scans,
            QKeySequence("Ctrl+I"),
            "Add scan files (LAS, LAZ, PLY, PCD, E57, XYZ)",
        )
        self.act_relink = a(
            "Re&link missing scans\u2026",
            self._ask_relink,
            None,
            "Point the project's scans that were moved at the folder that holds them now",
        )
        self.act_plan = a(
            "&Plan next scan",
            self.plan_next_scan,
            None,
            "Where the next scans should stand (forestreg plan), marked on the top view",
        )
        self.act_watch = a(
            "&Watch folder\u2026",
            self._ask_watch_folder,
            None,
            "Register each scan as the scanner's export folder fills (forestreg plot --watch)",
        )
        self.act_export_poses = a(
            "Export &transforms and poses\u2026",
            self._ask_export_poses,
            QKeySequence("Ctrl+E"),
            "Write poses.json and one <scan>.transform.txt per registered scan",
        )
        self.act_export_merged = a(
            "Export &merged LAZ\u2026", self._ask_export_merged, None, "Write all registered scans into one LAZ file"
        )
        self.act_export_scans = a(
            "Export registered &scans (one LAZ each)\u2026",
            self._ask_export_scans,
            None,
            "Write each registered scan in the centre scan's coordinates as its own LAZ file",
        )
        self.act_export_e57 = a(
            "Export registered &E57…",
            self._ask_export_e57,
            None,
            "Write the registered scans into one E57 file, each with its pose",
        )
        self.act_export_report = a(
            "Export HTML &report\u2026",
            self._ask_export_report,
            QKeySequence("Ctrl+Shift+E"),
            "Write the plot report (one HTML file)",
        )
        self.act_open_trees = a(
            "Open t&rees result\u2026",
            self._ask_open_trees,
            None,
            "Show the trees measured by 'forestreg trees --out DIR' (map, table, each tree in 3D)",
        )
        self.act_open_coreg = a(
            "Open &co-registration result\u2026",
            self._ask_open_coregistration,
            None,
            "Show a ground-based / UAV co-registration made by 'forestreg coregister --out DIR'",
        )
        self.act_open_change = a(
            "Open re-&survey result\u2026",
            self._ask_open_change,
            None,
            "Show two surveys of one plot compared by 'forestreg change BEFORE AFTER --out DIR'",
        )
        self.act_evaluate = a(
            "&Evaluate against field data\u2026",
            self._ask_evaluate,
            None,
            "Compare tree tables (e.g. ground-only and fused) with field records: R2, RMSE, rRMSE",
        )
        self.act_quit = a("&Quit", self.close, QKeySequence.StandardKey.Quit, "Close forestreg")
        self.act_run = a(
            "&Run registration", lambda: self.run(), QKeySequence("Ctrl+R"), "Register every scan not registered yet"
        )
        self.act_rerun = a(
            "Run &all links again",
            lambda: self.run(rerun=True),
            QKeySequence("Ctrl+Shift+R"),
            "Register every scan again, also those already registered",
        )
        self.act_cancel = a(
            "&Cancel", self.cancel_run, QKeySequence(Qt.Key.Key_Escape), "Stop the running registration"
        )
        self.act_cancel.setEnabled(False)
        self.act_before = a(
            "3D view &before registration",
            lambda: self.set_scene_mode("before"),
            QKeySequence("Ctrl+1"),
            "Each scan in its own coordinates",
            checkable=True,
        )
        self.act_after = a(
            "3D view &after registration",
            lambda: self.set_scene_mode("after"),
            QKeySequence("Ctrl+2"),
            "The scans in the project frame",
            checkable=True,
        )
        group = QActionGroup(self)
        group.addAction(self.act_before)
        group.addAction(self.act_after)
        self.act_before.setChecked(True)
        self.act_all_points = a(
            "Draw &all points (slower)",
            self._toggle_all_points,
            None,
            "Draw every point of every scan instead of a 200 000-point sample",
            checkable=True,
        )
        self.act_reset_camera = a(
            "Reset 3D &camera", self.scene_view.reset_camera, QKeySequence("Ctrl+0"), "Look at all points again"
        )
        self.act_top_camera = a(
            "3D &top view",
            self.scene_view.top_view,
            QKeySequence("Ctrl+3"),
            "Look straight down, north up: trunks seen twice mean a poor registration",
        )
        self.act_about = a("&About forestreg", self._about)
        for act in (self.act_new, self.act_open, self.act_save, self.act_add, self.act_run, self.act_cancel):
            act.setShortcutContext(Qt.ShortcutContext.WindowShortcut)

    def _build_menus(self) -> None:
        bar = self.menuBar()
        m = bar.addMenu("&File")
        for act in (self.act_new, self.act_open, self.act_sample):
            m.addAction(act)
        self.recent_menu = m.addMenu("Open &recent")
        m.addAction(self.act_open_trees)
        m.addAction(self.act_open_coreg)
        m.addAction(self.act_open_change)
        m.addAction(self.act_evaluate)
        m.addSeparator()
        m.addAction(self.act_save)
        m.addAction(self.act_save_as)
        m.addSeparator()
        m.addAction(self.act_add)
        m.addAction(self.act_relink)
        m.addAction(self.act_watch)
        m.addSeparator()
        for act in (
            self.act_export_poses,
            self.act_export_merged,
            self.act_export_scans,
            self.act_export_e57,
            self.act_export_report,
        ):
            m.addAction(act)
        m.addSeparator()
        m.addAction(self.act_quit)
        m = bar.addMenu("&Registration")
        for act in (self.act_run, self.act_rerun, self.act_cancel, self.act_plan):
            m.addAction(act)
        m = bar.addMenu("&View")
        for act in (self.act_before, self.act_after, self.act_all_points, self.act_reset_camera, self.act_top_camera):
            m.addAction(act)
        m.addSeparator()
        for dock in (self.tree_dock, self.params_dock, self.results_dock):
            m.addAction(dock.toggleViewAction())
        m = bar.addMenu("&Help")
        m.addAction(self.act_about)

        for act, name in (
            (self.act_open, "open"),
            (self.act_save, "save"),
            (self.act_add, "add"),
            (self.act_sample, "sample"),
            (self.act_run, "run"),
            (self.act_cancel, "cancel"),
            (self.act_before, "before"),
            (self.act_after, "after"),
            (self.act_export_poses, "export"),
            (self.act_export_report, "report"),
        ):
            act.setIcon(icon(name))
        self.setWindowIcon(icon("forestreg"))
        tb = self.addToolBar("Main")
        tb.setObjectName("toolbar-main")
        tb.setToolButtonStyle(Qt.ToolButtonStyle.ToolButtonTextBesideIcon)
        for act in (self.act_open, self.act_save, self.act_add, self.act_sample):
            tb.addAction(act)
        tb.addSeparator()
        for act in (self.act_run, self.act_cancel):
            tb.addAction(act)
        tb.addSeparator()
        for act in (self.act_before, self.act_after, self.act_top_camera):
            tb.addAction(act)
        tb.addSeparator()
        for act in (self.act_export_poses, self.act_export_report):
            tb.addAction(act)
        self.act_run.setIconText("Run")
        self.act_cancel.setIconText("Cancel")
        self.act_before.setIconText("Before")
        self.act_after.setIconText("After")
        self.act_top_camera.setIconText("Top view")
        self.act_export_poses.setIconText("Export transforms")
        self.act_export_report.setIconText("Report")
        self.act_open.setIconText("Open")
        self.act_save.setIconText("Save")
        self.act_add.setIconText("Add scans")
        self.act_sample.setIconText("Sample plot")

    def _build_status(self) -> None:
        self.status_label = QLabel("Ready")
        self.progress_bar = QProgressBar()
        self.progress_bar.setRange(0, 1000)
        self.progress_bar.setMaximumWidth(320)
        self.progress_bar.setTextVisible(True)
        self.progress_bar.hide()
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setToolTip("Stop the running registration (Esc)")
        self.cancel_button.clicked.connect(self.cancel_run)
        self.cancel_button.hide()
        sb = self.statusBar()
        sb.addWidget(self.status_label, 1)
        sb.addPermanentWidget(self.progress_bar)
        sb.addPermanentWidget(self.cancel_button)

    # ================================================================== project state

    @property
    def project(self) -> Project:
        return self.model.project

    def set_project(self, project: Project) -> None:
        """Show another project (nothing asked: see :meth:`confirm_discard`). The marks of the top
        view (a plan, the watcher's advice) stay when it is the same project, or its file read
        again (a watched plot folder updated), and go with any other."""
        from pathlib import Path

        old = self.project
        same = project is old or (
            project.path is not None and old.path is not None and Path(project.path) == Path(old.path)
        )
        if not same:
            self.top_view.clear_marks()
        self.model.set_project(project)
        self.scans = ScanCache(project)
        self.previews = PreviewCache(self.scans, budget=self.previews.budget)
        self._project_replaced()

    def _project_replaced(self) -> None:
        self.dirty = False
        self.last_outcome = None
        self.params_panel.set_params(self.project.params)
        self.tree.expandAll()
        self.tree.resizeColumnToContents(0)
        self._refresh_tables()
        registered = any(n != self.project.centre and p is not None for n, p in self.project.poses().items())
        self.set_scene_mode("after" if registered else "before", refresh=False)
        self.refresh_scene()
        self.refresh_top_view()
        self._restore_forest()
        self._update_title()
        self._update_actions()
        self.status_label.setText(self.summary())
        self._manual_refresh()
        if hasattr(self, "tie_view"):  # the side-by-side views are drawn again when next shown
            self.tie_view.scanners.clear()
            if self.bottom_tabs.currentWidget() is self.targets_tab:
                self.show_tie_points()
        self.projectLoaded.emit()

    def summary(self) -> str:
        """One line about the project: scans, and how many are placed."""
        p = self.project
        if not p.scans:
            return "Add the scans of a plot (File > Add scans) or open a project."
        placed = sum(1 for n, pose in p.poses().items() if pose is not None and n != p.centre)
        ran = any(link.result is not None for link in p.links)
        if not ran:
            return f"{len(p.scans)} scans, centre {p.centre}: press Run (Ctrl+R) to register them"
        return f"{len(p.scans)} scans, centre {p.centre}: {placed} of {len(p.scans) - 1} placed"

    def _project_edited(self) -> None:
        self.dirty = True
        self._refresh_tables()
        self._update_title()
        self._update_actions()
        self.refresh_scene()
        self.refresh_top_view()
        self._manual_refresh()

    def _params_edited(self, params: Any) -> None:
        if params != self.project.params:
            self.project.params = params
            self.dirty = True
            self._update_title()

    def _refresh_tables(self) -> None:
        self.link_table.show_project(self.project)
        self.scan_table.show_project(self.project)

    def _update_title(self) -> None:
        where = str(self.project.path) if self.project.path else "not saved"
        self.setWindowTitle(f"forestreg \u2013 {self.project.name} ({where})[*]")
        self.setWindowModified(self.dirty)

    def _update_actions(self) -> None:
        running = self.running
        has_scans = bool(self.project.scans)
        registered = (
            any(p is not None for n, p in self.project.poses().items() if n != self.project.centre)
            if has_scans
            else False
        )
        for act in (
            self.act_new,
            self.act_open,
            self.act_sample,
            self.act_add,
            self.act_save_as,
            self.act_watch,
            self.recent_menu.menuAction(),
        ):
            act.setEnabled(not running)
        self.act_save.setEnabled(not running)
        self.act_run.setEnabled(not running and len(self.project.scans) >= 2)
        self.act_rerun.setEnabled(not running and len(self.project.scans) >= 2)
        self.act_cancel.setEnabled(running)
        self.act_plan.setEnabled(not running and registered)
        for act in (
            self.act_export_poses,
            self.act_export_merged,
            self.act_export_scans,
            self.act_export_e57,
            self.act_export_report,
        ):
            act.setEnabled(not running and registered)
        self.params_panel.setEnabled(not running)
        self._manual_refresh()
        self.model.editable = not running
        self.tree.setDragEnabled(not running)

    @property
    def running(self) -> bool:
        return self.run_worker is not None

    # ================================================================== running

    def apply_panel_params(self) -> bool:
        """Put the parameter panel's values into the project; False (and the reason shown) when
        they are invalid."""
        try:
            self.project.params = self.params_panel.params()
        except ForestregError as exc:
            self.show_error("Invalid parameters", str(exc))
            return False
        return True

    def run(self, *, rerun: bool = False) -> bool:
        """Register the project in the background; False when it cannot start (and why is shown)."""
        if self.running:
            return False
        if len(self.project.scans) < 2:
            self.show_error("Nothing to register", "Add at least two scans to the project first.")
            return False
        if not self.apply_panel_params():
            return False
        worker = RegistrationWorker(self.project, self.scans, rerun=rerun)
        self.run_worker = worker
        self.last_error = None
        self._set_busy(True, "Registering\u2026")
        log.info("registration started (%d scans)", len(self.project.scans))
        self.tasks.start(
            worker,
            succeeded=self._run_finished,
            failed=self._run_failed,
            cancelled=self._run_cancelled,
            progress=self._show_progress,
            link_done=self._link_done,
            ended=self._run_ended,
        )
        return True

    def cancel_run(self) -> None:
        """Ask the running registration to stop (it stops at the engine's next check)."""
        if self.run_worker is not None:
            self.run_worker.cancel()
            self.status_label.setText("Cancelling\u2026 (the current step finishes first)")
            self.cancel_button.setEnabled(False)
            log.info("cancelling the registration")

    def _show_progress(self, fraction: float, message: str) -> None:
        self.progress_bar.show()
        self.progress_bar.setValue(int(round(1000 * fraction)))
        self.progress_bar.setFormat(f"{100 * fraction:.0f} %")
        if message and not (self.run_worker is not None and self.run_worker.token.cancelled):
            self.status_label.setText(message)

    def _link_done(self, moving: str) -> None:
        self.model.refresh()
        self._refresh_tables()

    def _run_finished(self, outcome: Any) -> None:
        self.last_outcome = outcome
        placed = len(outcome.registered) - 1 if outcome.registered else 0
        failed = outcome.failed
        text = f"Registration finished: {placed} of {len(self.project.scans) - 1} scans placed"
        if failed:
            text += f"; not placed: {', '.join(failed)}"
        log.info("%s", text)
        self.status_label.setText(text)
        self.runFinished.emit(outcome)

    def _run_failed(self, message: str, details: str) -> None:
        self.status_label.setText("Registration failed")
        self.show_error("The registration failed", message, details)
        self.runFailed.emit(message, details)

    def _run_cancelled(self) -> None:
        self.status_label.setText("Registration cancelled; links finished before are kept")
        self.runCancelled.emit()

    def _run_ended(self) -> None:
        self.run_worker = None
        self._set_busy(False)
        self.dirty = self.project.path is None or self.dirty
        self.model.refresh()
        self._refresh_tables()
        self._update_title()
        registered = any(p is not None for n, p in self.project.poses().items() if n != self.project.centre)
        self.set_scene_mode("after" if registered else self.scene_mode, refresh=False)
        self.refresh_scene()
        self.refresh_top_view()
        self.bottom_tabs.setCurrentWidget(self.link_table)

    def _set_busy(self, busy: bool, text: str = "") -> None:
        self.progress_bar.setVisible(busy)
        self.progress_bar.setValue(0)
        self.cancel_button.setVisible(busy)
        self.cancel_button.setEnabled(busy)
        if text:
            self.status_label.setText(text)
        self._update_actions()

    # ================================================================== views

    def set_scene_mode(self, mode: str, *, refresh: bool = True) -> None:
        """Show the scans "before" (own coordinates) or "after" (project frame) registration."""
        self.scene_mode = mode
        (self.act_after if mode == "after" else self.act_before).setChecked(True)
        if refresh:
            self.refresh_scene()

    def _toggle_all_points(self) -> None:
        from .scene_data import DEFAULT_POINT_BUDGET

        self.previews.budget = 2**62 if self.act_all_points.isChecked() else DEFAULT_POINT_BUDGET
        self.refresh_scene()

    def refresh_scene(self) -> None:
        """Rebuild the 3D view in the background (reads the scans once)."""
        self._start_view_task("3D view", self._scene_task, self._scene_built)

    def _scene_task(self) -> TaskWorker:
        project, previews, mode = self.project, self.previews, self.scene_mode
        return TaskWorker(lambda progress, cancel: build_scene(project, previews, mode, progress), name="3D view")

    def _scene_built(self, scene: Any) -> None:
        if scene.mode != self.scene_mode or self.scene_view.plotter is None:
            return
        self.scene_view.show_scene(scene)
        for name, why in scene.missing.items():
            if why != "not registered":
                log.warning("%s cannot be drawn: %s", name, why)
        self.sceneReady.emit()

    def refresh_top_view(self) -> None:
        """Recompute the top view (slices, VOPs, matches) in the background: once a link is made,
        or while the map has marks (a plan, the watcher's advice) to show over the placed scans."""
        if not any(link.ok for link in self.project.links) and not self.top_view.has_marks:
            self.top_view.show_message(
                "Run the registration to see the slices, trunk shadows (VOPs) and matches."
                if self.project.scans
                else "Add scans or open a project."
            )
            self.topViewReady.emit()
            return
        self._start_view_task("top view", self._top_task, self._top_built)

    def _top_task(self) -> TaskWorker:
        from ..engine.report.views import compute_top_view

        project, scans = self.project, self.scans
        return TaskWorker(lambda progress, cancel: compute_top_view(project, scans), name="top view")

    def _top_built(self, view: Any) -> None:
        from ..engine.report.views import scan_colours
        from .top_view import SurveyOverlay

        self.top_view.show_view(
            view,
            scan_colours(self.project),
            title=f"{self.project.name}: trunk shadows, matches and pose uncertainty",
            overlay=SurveyOverlay.of(self.project),
        )
        self.topViewReady.emit()

    def _start_view_task(self, name: str, make: Callable[[], TaskWorker], done: Callable[[Any], None]) -> None:
        """One view task at a time; a request while one runs is done once it ends."""
        if self.tasks.busy(name):
            self._pending.add(name)
            return
        project = self.project

        def succeeded(result: Any) -> None:
            if project is self.project and name not in self._pending:
                done(result)

        def ended() -> None:
            if name in self._pending:
                self._pending.discard(name)
                self._start_view_task(name, make, done)

        self._start_task(
            make(),
            succeeded=succeeded,
            ended=ended,
            failed=lambda m, d: log.warning("the %s could not be drawn: %s", name, m),
        )

    def _start_task(self, worker: TaskWorker, **callbacks: Any) -> None:
        self.tasks.start(worker, **callbacks)

    @property
    def busy(self) -> bool:
        """Whether any background work (run, views, exports) is going on."""
        return self.tasks.busy()

    # ================================================================== tree menu

    def _tree_menu(self, pos: QPoint) -> None:
        index = self.tree.indexAt(pos)
        menu = self.tree_menu(index)
        if menu is not None:
            menu.exec(self.tree.viewport().mapToGlobal(pos))

    def tree_menu(self, index: QModelIndex) -> Optional[QMenu]:
        """The context menu for a tree row (None where there is nothing to do)."""
        if self.running:
            return None
        menu = QMenu(self)
        name = self.model.scan_name(index)
        link = self.model.link_at(index)
        p = self.project
        if name is not None:
            entry = p.scan(name)
            act = menu.addAction("Mark as centre scan", lambda: self._edit(self.model.set_centre, name))
            act.setEnabled(name != p.centre)
            if entry.tilted:
                menu.addAction("Mark as level (not tilted)", lambda: self._edit(self.model.set_tilted, name, False))
            else:
                menu.addAction(
                    "Mark as tilted (partner found by the run)", lambda: self._edit(self.model.set_tilted, name, True)
                )
            others = [s.name for s in p.scans if s.name != name]
            beside = menu.addMenu("Tilted, beside")
            for other in others:
                beside.addAction(other, lambda o=other: self._edit(self.model.set_tilted, name, True, o))
            to = menu.addMenu("Link to (register onto)")
            to.setEnabled(name != p.centre)
            for other in others:
                to.addAction(other, lambda o=other: self._edit(self.model.link, name, o))
            menu.addSeparator()
            menu.addAction("Forget its result", lambda: self._edit(self.model.clear_results, [name]))
            menu.addAction("Remove from project", lambda: self._edit(self.model.remove_scan, name))
        elif link is not None:
            menu.addAction(
                "Forget the result (run it again with Run)", lambda: self._edit(self.model.clear_results, [link.moving])
            )
            self._link_method_actions(menu, link)
        else:
            menu.addAction(self.act_add)
            menu.addAction(self.act_run)
        return menu

    def _edit(self, fn: Callable[..., Any], *args: Any) -> None:
        try:
            fn(*args)
        except (KeyError, ValueError, ForestregError) as exc:
            self.show_error("Cannot change the project", str(exc).strip("'\""))

    # ================================================================== messages

    def show_error(self, title: str, message: str, details: str = "") -> None:
        """A readable message box (non-blocking) with the technical details folded away."""
        self.last_error = (title, message, details)
        log.error("%s: %s", title, message)
        if not self.interactive:
            return
        box = QMessageBox(QMessageBox.Icon.Warning, title, message, QMessageBox.StandardButton.Ok, self)
        if details:
            box.setDetailedText(details)
        box.setWindowModality(Qt.WindowModality.WindowModal)
        box.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
        self.error_box = box
        box.open()

    def _about(self) -> None:
        QMessageBox.about(
            self,
            "About forestreg",
            "forestreg registers terrestrial laser scans of forest plots without targets, from the "
            "shadows that tree trunks cast in the scans (Guan et al. 2020).\n\n"
            "Add the scans of a plot, mark the centre scan, press Run (Ctrl+R), then export the "
            "transforms or the report.",
        )

    def showEvent(self, event: Any) -> None:  # noqa: N802 - Qt API
        super().showEvent(event)
        if not getattr(self, "_docks_sized", False) and not isinstance(self.settings.value("window/state"), QByteArray):
            # first show without a saved layout: the results tables get a fifth of the height, not half
            self._docks_sized = True
            # after the first layout pass (sizing during showEvent is overridden by it)
            QTimer.singleShot(
                0,
                lambda: self.resizeDocks([self.results_dock], [max(150, self.height() // 5)], Qt.Orientation.Vertical),
            )

    def closeEvent(self, event: QCloseEvent) -> None:  # noqa: N802 - Qt API
        if self.running and self.interactive:
            answer = QMessageBox.question(self, "Registration running", "A registration is running. Stop it and close?")
            if answer != QMessageBox.StandardButton.Yes:
                event.ignore()
                return
        if not self.confirm_discard():
            event.ignore()
            return
        self.tasks.cancel_all()
        if not self.tasks.wait_all(5000):
            # the engine is inside a step that does not check for cancelling yet: close once it
            # ends (a thread must not be destroyed while it runs)
            self.hide()
            self.interactive = False
            self.tasks.idle.connect(self.close)
            event.ignore()
            return
        self.save_settings()
        self.log_pane.detach()
        self.scene_view.close_view()
        self.trees_view.scene3d.close_view()
        self.tie_view.close_views()
        event.accept()
