"""The main window's System B tabs: "Co-registration" (ground-based cloud onto a UAV/ALS cloud, then
fusion) and "Trees" (the inventory map, table and the selected tree). Result folders are read with
:mod:`forestreg.engine.io.results`; runs go through :class:`~forestreg.ui.worker.TaskWorker`."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional

from PySide6.QtWidgets import QFileDialog, QTabWidget

from ..engine.core.errors import ForestregError
from .change_view import ChangeView
from .coreg_view import CoregistrationView, shown_from_folder
from .evaluation_view import EvaluationView
from .trees_view import TreesView

log = logging.getLogger("forestreg")

#: Tab titles of the central area.
TAB_TLS, TAB_COREG, TAB_TREES, TAB_EVAL = "TLS registration", "Co-registration", "Trees", "Field data"
TAB_CHANGE = "Re-survey"


class SystemBMixin:
    """Adds the co-registration and trees tabs to :class:`~forestreg.ui.main_window.MainWindow`."""

    def _build_system_b(self, tls_view: Any) -> QTabWidget:
        """Wrap the TLS views in a tab widget with the System B tabs; returns it (the central widget)."""
        self.central_tabs = QTabWidget()
        self.central_tabs.setObjectName("central-tabs")
        self.central_tabs.setDocumentMode(True)
        self.central_tabs.addTab(tls_view, TAB_TLS)
        self.coreg_view = CoregistrationView(start_task=self._start_task)
        self.central_tabs.addTab(self.coreg_view, TAB_COREG)
        self.trees_view = TreesView(renderer=self._renderer_choice(), start_task=self._start_task)
        self.central_tabs.addTab(self.trees_view, TAB_TREES)
        self.evaluation_view = EvaluationView()
        self.central_tabs.addTab(self.evaluation_view, TAB_EVAL)
        self.change_view = ChangeView()
        self.central_tabs.addTab(self.change_view, TAB_CHANGE)
        self.coreg_view.run_button.clicked.connect(self._ask_coregister)
        self.coreg_view.fuse_button.clicked.connect(self._ask_fuse)
        self.coreg_view.decided.connect(self._coreg_decided)
        self.coreg_view.fused.connect(self._coreg_fused)
        self.trees_view.edited.connect(self._trees_edited)
        self.trees_points_file: Optional[str] = None
        self._tls_docks_visible: Optional[dict[Any, bool]] = None
        self.central_tabs.currentChanged.connect(self._tab_changed)
        return self.central_tabs

    def _tab_changed(self, index: int) -> None:
        """The TLS docks (project tree, parameters, results) belong to the TLS tab: hidden on the
        System B tabs so that the map, table and 3D view get the room, shown again on return."""
        hints = {
            TAB_COREG: "Co-registration: open a result (File menu) or Co-register\u2026 a ground-based and a UAV cloud",
            TAB_TREES: "Trees: click a tree on the map or in the table; Measure trees\u2026 to correct them",
            TAB_EVAL: "Field data: File \u25b8 Evaluate against field data\u2026",
        }
        label = getattr(self, "status_label", None)
        title = self.central_tabs.tabText(index)
        if label is not None and title in hints:
            label.setText(hints[title])
        docks = [
            d
            for d in (
                getattr(self, "tree_dock", None),
                getattr(self, "params_dock", None),
                getattr(self, "results_dock", None),
            )
            if d is not None
        ]
        if self.central_tabs.widget(index) is self.view_splitter:
            if self._tls_docks_visible is not None:
                for d in docks:
                    d.setVisible(self._tls_docks_visible.get(d, True))
                self._tls_docks_visible = None
        elif self._tls_docks_visible is None:
            self._tls_docks_visible = {d: d.isVisible() for d in docks}
            for d in docks:
                d.hide()

    # ------------------------------------------------------------------ the project's System B part

    def _forest_changed(self) -> None:
        """A System B result was opened or decided: the project holds it (saved with the project)."""
        self.dirty = True
        self._update_title()

    def _restore_forest(self) -> None:
        """Show what a loaded project's System B part names (folders that no longer exist are skipped)."""
        forest = self.project.forest
        self.trees_view.inventory = None
        self.trees_view.steps = []
        if forest.coregistration is not None and (forest.coregistration / "result.json").is_file():
            self._show_coregistration(forest.coregistration, forest.coregistration_decision)
        for name, folder in forest.trees.items():
            if (folder / "trees.csv").is_file():
                cloud = (
                    forest.fused_cloud
                    if name == "fused" and forest.fused_cloud and forest.fused_cloud.is_file()
                    else None
                )
                self._show_trees(folder, cloud)
                break
        if self.project.scans or forest.empty:
            self.show_tab(TAB_TLS)

    def show_tab(self, title: str) -> None:
        for k in range(self.central_tabs.count()):
            if self.central_tabs.tabText(k) == title:
                self.central_tabs.setCurrentIndex(k)
                return

    def current_scene_view(self) -> Any:
        """The 3D view on the visible tab (for screenshots)."""
        if self.central_tabs.currentWidget() is self.trees_view:
            return self.trees_view.scene3d
        return self.scene_view

    # ------------------------------------------------------------------ trees

    def open_trees(
        self, folder: str | Path, cloud: Optional[str | Path] = None, *, select: Optional[int] = None
    ) -> bool:
        """Show a ``forestreg trees --out DIR`` folder; ``cloud`` the measured cloud (optional: its
        points around the selected tree are drawn). False with :attr:`last_error` on failure."""
        if not self._show_trees(folder, cloud, select=select):
            return False
        forest = self.project.forest
        forest.trees[Path(folder).name] = Path(folder).resolve()
        self._forest_changed()
        self.show_tab(TAB_TREES)
        return True

    def _show_trees(
        self, folder: str | Path, cloud: Optional[str | Path] = None, *, select: Optional[int] = None
    ) -> bool:
        from ..app.trees import read_trees_folder
        from ..engine.io import read_scan

        try:
            out = read_trees_folder(folder)
            points = read_scan(cloud).file_points if cloud else None
        except ForestregError as exc:
            self.show_error("Cannot open the trees result", str(exc))
            return False
        self.trees_points_file = str(cloud) if cloud else None
        self.trees_view.inventory = None  # a folder's trees are shown; edits need them measured here
        self.trees_view.steps = []
        self.trees_view.show_output(out, points, select=select)
        log.info("trees: %d trees from %s", len(out.trees), folder)
        return True

    # ------------------------------------------------------------------ co-registration

    def open_coregistration(self, folder: str | Path) -> bool:
        """Show a ``forestreg coregister --out DIR`` folder. False with :attr:`last_error` on failure."""
        if not self._show_coregistration(folder):
            return False
        forest = self.project.forest
        forest.coregistration = Path(folder).resolve()
        forest.coregistration_decision = ""
        shown = self.coreg_view.shown
        if shown is not None and shown.ground_file:
            forest.ground_cloud = Path(shown.ground_file)
            forest.uav_clouds = [Path(shown.uav_file)] if shown.uav_file else []
        self._forest_changed()
        self.show_tab(TAB_COREG)
        return True

    def _show_coregistration(self, folder: str | Path, decision: str = "") -> bool:
        from ..app.coregistration import read_coregistration_folder

        try:
            out, summary = read_coregistration_folder(folder)
        except ForestregError as exc:
            self.show_error("Cannot open the co-registration result", str(exc))
            return False
        shown = shown_from_folder(out, summary)
        self.coreg_view.show_result(shown)
        if decision:
            self.coreg_view.decide(decision)
        log.info("co-registration %s: %s", folder, "ok" if summary.ok else summary.reason)
        return True

    def _coreg_decided(self, decision: str) -> None:
        self.project.forest.coregistration_decision = decision
        self._forest_changed()

    def _coreg_fused(self, _counts: Any) -> None:
        path = self.coreg_view.fused_path
        if path:
            self.project.forest.fused_cloud = Path(path).resolve()
            self._forest_changed()

    def _trees_edited(self, _note: str) -> None:
        self.project.forest.tree_edits = [e.to_dict() for e, _ in self.trees_view.steps]
        self._forest_changed()

    # ------------------------------------------------------------------ field data

    def evaluate_field(self, field_csv: str | Path, runs: dict[str, str | Path]) -> bool:
        """Compare tree tables (``runs``: name -> trees.csv or a trees folder) with a field CSV
        (the engine's matching and figures) and show them side by side on the Field data tab."""
        from ..app.evaluation import evaluate_files

        try:
            results = evaluate_files(runs, field_csv)
        except ForestregError as exc:
            self.show_error("Cannot evaluate", str(exc))
            return False
        self.evaluation_view.show_evaluations(results, Path(field_csv).name)
        self.project.forest.field_data = Path(field_csv).resolve()
        for name, path in runs.items():
            p = Path(path).resolve()
            self.project.forest.trees.setdefault(name, p if p.is_dir() else p.parent)
        self._forest_changed()
        self.show_tab(TAB_EVAL)
        return True

    def _ask_evaluate(self) -> None:
        field, _ = QFileDialog.getOpenFileName(
            self, "Field data (CSV: tree id, x, y, DBH, height, ...)", self._last_dir(), "CSV (*.csv);;All files (*)"
        )
        if not field:
            return
        runs: dict[str, str] = {}
        while True:
            folder = QFileDialog.getExistingDirectory(
                self, f"Trees result folder {len(runs) + 1} (cancel when done)", str(Path(field).parent)
            )
            if not folder:
                break
            runs[Path(folder).name] = folder
        if runs:
            self.evaluate_field(field, runs)

    def _ask_open_trees(self) -> None:
        folder = QFileDialog.getExistingDirectory(
            self, "Trees result folder (forestreg trees --out DIR)", self._last_dir()
        )
        if folder:
            cloud, _ = QFileDialog.getOpenFileName(
                self,
                "The measured cloud (optional: cancel to skip)",
                self._last_dir(),
                "Point clouds (*.las *.laz *.ply *.pcd *.xyz *.txt *.e57)",
            )
            self.open_trees(folder, cloud or None)

    def open_change(self, folder: str | Path) -> bool:
        """Show a ``forestreg change --out DIR`` folder (re-survey). False with :attr:`last_error`
        on failure."""
        from ..engine.io.change import read_change_dir

        try:
            out = read_change_dir(folder)
        except ForestregError as exc:
            self.show_error("Cannot open the re-survey result", str(exc))
            return False
        self.change_view.show_output(out)
        self.show_tab(TAB_CHANGE)
        log.info("re-survey: %d trees from %s", len(out.rows), folder)
        return True

    def _ask_open_change(self) -> None:
        folder = QFileDialog.getExistingDirectory(
            self, "Re-survey result folder (forestreg change --out DIR)", self._last_dir()
        )
        if folder:
            self.open_change(folder)

    def _ask_open_coregistration(self) -> None:
        folder = QFileDialog.getExistingDirectory(
            self, "Co-registration result folder (forestreg coregister --out DIR)", self._last_dir()
        )
        if folder:
            self.open_coregistration(folder)

    def _ask_coregister(self) -> None:
        filt = "Point clouds (*.las *.laz *.ply *.pcd *.xyz *.txt *.e57)"
        ground, _ = QFileDialog.getOpenFileName(
            self, "Ground-based cloud (TLS plot, backpack, handheld)", self._last_dir(), filt
        )
        if not ground:
            return
        uav, _ = QFileDialog.getOpenFileName(self, "UAV or airborne cloud", str(Path(ground).parent), filt)
        if uav:
            self.coreg_view.run(ground, uav)

    def _ask_fuse(self) -> None:
        start = (
            str(Path(self.coreg_view.shown.ground_file).with_name("fused.laz"))
            if self.coreg_view.shown
            else "fused.laz"
        )
        path, _ = QFileDialog.getSaveFileName(self, "Fused cloud", start, "LAZ (*.laz);;LAS (*.las)")
        if path:
            self.coreg_view.fuse(path)
