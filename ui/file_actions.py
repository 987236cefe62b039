"""File actions of the main window: new/open/save projects, add scans, the sample plot, exports
(transforms, merged LAZ, registered E57, HTML report), recent files and window settings.

A mixin of :class:`~forestreg.ui.main_window.MainWindow` (it uses the window's project, model,
tasks and messages); exports run in the background through the engine's writers.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from PySide6.QtCore import QByteArray, QUrl
from PySide6.QtGui import QDesktopServices
from PySide6.QtWidgets import QFileDialog, QMessageBox

from ..app.plot import Project
from ..engine.core.errors import ForestregError
from ..engine.io import SUPPORTED_READ_SUFFIXES
from .worker import TaskWorker, describe_error

log = logging.getLogger("forestreg")

MAX_RECENT = 8
PROJECT_FILTER = "forestreg projects (*.json);;All files (*)"


def scan_file_filter() -> str:
    """The file dialog filter for scans, from the engine's readable suffixes."""
    patterns = " ".join(f"*{s}" for s in SUPPORTED_READ_SUFFIXES)
    return f"Point clouds ({patterns});;All files (*)"


class FileActionsMixin:
    """Project files, scans, exports and settings of the main window."""

    # ================================================================== files

    def new_project(self) -> None:
        if self.running or not self.confirm_discard():
            return
        self.set_project(Project(name="untitled"))
        log.info("new project")

    def open_project(self, path: str | Path) -> bool:
        """Open a project file; a damaged one is refused with the engine's message."""
        if self.running:
            return False
        try:
            project = Project.load(path)
        except ForestregError as exc:
            self.show_error("Cannot open the project", str(exc), describe_error(exc)[1])
            self._forget_recent(Path(path))
            return False
        self.set_project(project)
        self._add_recent(project.path)
        log.info("opened %s (%d scans)", project.path, len(project.scans))
        if self.missing_scans():
            self._report_missing_scans()
        return True

    def missing_scans(self) -> list:
        """The project's scans whose files are not where the project says (moved or deleted)."""
        return [s for s in self.project.scans if not Path(s.path).is_file()]

    def _report_missing_scans(self) -> None:
        """A clear message naming the missing files; interactively, an offer to relink them."""
        missing = self.missing_scans()
        names = "\n".join(f"  {s.name}: {s.path}" for s in missing[:20]) + ("\n  ..." if len(missing) > 20 else "")
        message = (
            f"{len(missing)} of the {len(self.project.scans)} scans of this project are not where it says "
            f"(moved or deleted):\n{names}\n\nPoint the project at the folder that holds them now with "
            "File > Relink missing scans…"
        )
        if not self.interactive:
            self.show_error("Scans not found", message)
            return
        answer = QMessageBox.question(
            self,
            "Scans not found",
            message + "\n\nChoose that folder now?",
            QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No,
            QMessageBox.StandardButton.Yes,
        )
        self.last_error = ("Scans not found", message, "")
        if answer == QMessageBox.StandardButton.Yes:
            self._ask_relink()

    def _ask_relink(self) -> None:
        if not self.missing_scans():
            self.statusBar().showMessage("Every scan of the project is where it says", 5000)
            return
        folder = QFileDialog.getExistingDirectory(self, "Folder that holds the missing scans now", self._last_dir())
        if folder:
            self.relink_scans(folder)

    def relink_scans(self, folder: str | Path) -> list[str]:
        """Point the missing scans at files of the same name in ``folder`` (or a subfolder, two
        levels down); the project is changed (save it to keep the new places). Returns the names
        relinked; the ones still missing are named in a message."""
        folder = Path(folder)
        if self.running:
            return []
        found: list[str] = []
        for s in self.missing_scans():
            candidates = (
                [folder / s.path.name]
                + sorted(folder.glob(f"*/{s.path.name}"))
                + sorted(folder.glob(f"*/*/{s.path.name}"))
            )
            hit = next((c for c in candidates if c.is_file()), None)
            if hit is not None:
                s.path = hit.resolve()
                found.append(s.name)
        if found:
            self.set_project(self.project)  # fresh caches: the scans are read from their new places
            self.dirty = True
            self._update_title()
            log.info("relinked %s to %s", ", ".join(found), folder)
            self.statusBar().showMessage(f"Relinked {len(found)} scans to {folder}", 5000)
        still = self.missing_scans()
        if still:
            self.show_error(
                "Scans not found",
                f"{len(still)} scans are not in {folder} either: " + ", ".join(s.path.name for s in still),
            )
        else:
            self.last_error = None
        return found

    def save_project(self, path: Optional[str | Path] = None) -> bool:
        """Save atomically (``Project.save``); to ``path`` or the project's own file."""
        if path is None and self.project.path is None:
            return self._ask_save_as()
        try:
            if path is not None and self.project.path is None and self.project.name in ("untitled", "plot"):
                self.project.name = Path(path).stem.replace(".forestreg", "")
            saved = self.project.save(path)
        except (ForestregError, OSError) as exc:
            message, details = describe_error(exc)
            self.show_error("Cannot save the project", message, details)
            return False
        self.dirty = False
        self._add_recent(saved)
        self._update_title()
        self.statusBar().showMessage(f"Saved {saved}", 5000)
        log.info("saved %s", saved)
        return True

    def add_scans(self, paths: Sequence[str | Path]) -> list[str]:
        """Add scan files to the project (they are read when drawn or registered)."""
        missing = [str(p) for p in paths if not Path(p).is_file()]
        if missing:
            self.show_error("Cannot add scans", "These files do not exist:\n" + "\n".join(missing))
            paths = [p for p in paths if Path(p).is_file()]
        names = self.model.add_scans(paths)
        if names:
            log.info("added %s", ", ".join(names))
        return names

    def open_sample(self) -> None:
        """Open the simulated sample plot, simulating it first (in the background) if needed."""
        from .sample import make_sample_project

        if self.running or not self.confirm_discard():
            return
        self._start_task(
            TaskWorker(
                lambda progress, cancel: make_sample_project(progress=progress, cancel=cancel), name="sample plot"
            ),
            succeeded=lambda path: self.open_project(path),
            failed=lambda m, d: self.show_error("Cannot make the sample plot", m, d),
            progress=self._show_progress,
        )

    def confirm_discard(self) -> bool:
        """True when unsaved changes may be dropped (asks the user in interactive mode)."""
        if not self.dirty or not self.interactive or not self.project.scans:
            return True
        answer = QMessageBox.question(
            self,
            "Unsaved changes",
            f"The project {self.project.name} has unsaved changes. Save them first?",
            QMessageBox.StandardButton.Save | QMessageBox.StandardButton.Discard | QMessageBox.StandardButton.Cancel,
            QMessageBox.StandardButton.Save,
        )
        if answer == QMessageBox.StandardButton.Save:
            return self.save_project()
        return answer == QMessageBox.StandardButton.Discard

    # ---------------------------------------------------------------- dialogs

    def _last_dir(self) -> str:
        return str(self.settings.value("paths/last_dir", str(Path.home())))

    def _remember_dir(self, path: str | Path) -> None:
        p = Path(path)
        self.settings.setValue("paths/last_dir", str(p if p.is_dir() else p.parent))

    def _ask_open(self) -> None:
        if not self.confirm_discard():
            return
        path, _ = QFileDialog.getOpenFileName(self, "Open project", self._last_dir(), PROJECT_FILTER)
        if path:
            self._remember_dir(path)
            self.open_project(path)

    def _save(self) -> None:
        self.save_project()

    def _ask_save_as(self) -> bool:
        start = (
            str(self.project.path) if self.project.path else str(Path(self._last_dir()) / f"{self.project.name}.json")
        )
        path, _ = QFileDialog.getSaveFileName(self, "Save project", start, PROJECT_FILTER)
        if not path:
            return False
        if not Path(path).suffix:
            path += ".json"
        self._remember_dir(path)
        return self.save_project(path)

    def _ask_add_scans(self) -> None:
        paths, _ = QFileDialog.getOpenFileNames(self, "Add scans", self._last_dir(), scan_file_filter())
        if paths:
            self._remember_dir(paths[0])
            self.add_scans(paths)

    def _ask_load_params(self) -> None:
        path, _ = QFileDialog.getOpenFileName(
            self, "Load parameters", self._last_dir(), "Parameter files (*.toml);;All files (*)"
        )
        if path:
            try:
                self.params_panel.load_toml(path)
            except ForestregError as exc:
                self.show_error("Cannot read the parameters", str(exc))

    def _ask_folder(self, title: str, then: Callable[[str], None]) -> None:
        """Ask for a folder; if one is chosen, remember it as the last folder and call ``then(folder)``."""
        folder = QFileDialog.getExistingDirectory(self, title, self._last_dir())
        if folder:
            self._remember_dir(folder)
            then(folder)

    def _ask_save(self, title: str, default_name: str, filters: str, then: Callable[[str], None]) -> None:
        """Ask for a file to write; if one is chosen, remember its folder and call ``then(path)``."""
        path, _ = QFileDialog.getSaveFileName(self, title, str(Path(self._last_dir()) / default_name), filters)
        if path:
            self._remember_dir(path)
            then(path)

    def _ask_export_poses(self) -> None:
        self._ask_folder("Folder for poses.json and the transforms", self.export_poses)

    def _ask_export_merged(self) -> None:
        self._ask_save("Merged point cloud", "merged.laz", "LAZ (*.laz);;LAS (*.las);;PLY (*.ply)", self.export_merged)

    def _ask_export_scans(self) -> None:
        self._ask_folder("Folder for the registered scans (one LAZ each)", self.export_scans)

    def _ask_export_e57(self) -> None:
        self._ask_save("Registered scans", "registered.e57", "E57 (*.e57)", self.export_e57)

    def _ask_export_report(self) -> None:
        self._ask_save(
            "HTML report",
            "report.html",
            "HTML (*.html)",
            lambda path: self.export_report(path, open_after=self.interactive),
        )

    # ---------------------------------------------------------------- exports

    def _export(self, name: str, write: Callable[[], Any], done: Callable[[Any], None], failure: str) -> None:
        """Run ``write()`` in the background as task ``name``; ``done(result)`` on success, an
        error dialog titled ``failure`` otherwise."""
        self._start_task(
            TaskWorker(lambda progress, cancel: write(), name=name),
            succeeded=done,
            failed=lambda m, d: self.show_error(failure, m, d),
        )

    def export_poses(self, folder: str | Path) -> None:
        """``write_poses`` into ``folder`` (in the background)."""
        from ..app.plot import write_poses

        project, outcome = self.project, self.last_outcome
        self._export(
            "export transforms",
            lambda: write_poses(project, folder, outcome),
            lambda path: self._exported(f"Wrote {path} and the transforms"),
            "Cannot export the transforms",
        )

    def export_merged(self, path: str | Path) -> None:
        """``write_merged`` to ``path`` (in the background)."""
        from ..app.plot import write_merged

        project, scans = self.project, self.scans
        self._export(
            "export merged",
            lambda: write_merged(project, path, scans),
            lambda count: self._exported(f"Wrote {count:,} points to {path}"),
            "Cannot export the merged cloud",
        )

    def export_scans(self, folder: str | Path) -> None:
        """``write_registered_scans`` into ``folder`` (in the background)."""
        from ..app.plot import write_registered_scans

        project, scans = self.project, self.scans
        self._export(
            "export scans",
            lambda: write_registered_scans(project, folder, scans),
            lambda count: self._exported(f"Wrote {count} registered scans to {folder}"),
            "Cannot export the registered scans",
        )

    def export_e57(self, path: str | Path) -> None:
        """``write_registered_e57`` to ``path`` (in the background)."""
        from ..app.plot import write_registered_e57

        project, scans = self.project, self.scans
        self._export(
            "export e57",
            lambda: write_registered_e57(project, path, scans),
            lambda count: self._exported(f"Wrote {count} registered scans to {path}"),
            "Cannot export the E57 file",
        )

    def export_report(self, path: str | Path, *, open_after: bool = False) -> None:
        """``write_plot_report`` to ``path`` (in the background); opens it in the browser if asked."""
        from ..engine.report.plot_report import write_plot_report

        project, scans = self.project, self.scans

        def done(_: Any) -> None:
            self._exported(f"Wrote the report {path}")
            if open_after:
                QDesktopServices.openUrl(QUrl.fromLocalFile(str(Path(path).resolve())))

        self._export(
            "export report", lambda: write_plot_report(project, path, scans=scans), done, "Cannot write the report"
        )

    def _exported(self, text: str) -> None:
        log.info("%s", text)
        self.statusBar().showMessage(text, 8000)

    # ================================================================== settings

    def recent_files(self) -> list[str]:
        value = self.settings.value("recent/files", [])
        if isinstance(value, str):
            value = [value]
        return [str(v) for v in (value or [])]

    def _add_recent(self, path: Optional[Path]) -> None:
        if path is None:
            return
        files = [str(Path(path).resolve())] + [f for f in self.recent_files() if f != str(Path(path).resolve())]
        self.settings.setValue("recent/files", files[:MAX_RECENT])
        self._fill_recent_menu()

    def _forget_recent(self, path: Path) -> None:
        files = [f for f in self.recent_files() if f != str(Path(path).resolve())]
        self.settings.setValue("recent/files", files)
        self._fill_recent_menu()

    def _fill_recent_menu(self) -> None:
        self.recent_menu.clear()
        files = self.recent_files()
        for k, f in enumerate(files):
            act = self.recent_menu.addAction(f"&{k + 1} {f}")
            act.triggered.connect(lambda checked=False, f=f: self.confirm_discard() and self.open_project(f))
        self.recent_menu.setEnabled(bool(files))

    def _restore_settings(self) -> None:
        geometry = self.settings.value("window/geometry")
        state = self.settings.value("window/state")
        if isinstance(geometry, QByteArray):
            self.restoreGeometry(geometry)
        if isinstance(state, QByteArray):
            self.restoreState(state)
        self._fill_recent_menu()

    def save_settings(self) -> None:
        self.settings.setValue("window/geometry", self.saveGeometry())
        self.settings.setValue("window/state", self.saveState())
        self.settings.sync()
