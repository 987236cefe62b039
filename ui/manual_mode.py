"""Manual mode of the main window: targets per scan (table, CSV, detected reflectors, points picked
in the 3D view), the per-link method (auto | manual), manual registration and the comparison of
both methods (the paper's tables 4 and 5).

A mixin of :class:`~forestreg.ui.main_window.MainWindow`. The engine does the work
(:mod:`forestreg.engine.tls.manual`, :func:`forestreg.engine.tls.compare.compare_auto_manual`,
:func:`forestreg.engine.tls.plot.register_project` for manual links); this only edits
``ScanEntry.targets`` and ``Link.method`` and shows the results.
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np
from PySide6.QtCore import QPoint, Qt, QTimer
from PySide6.QtWidgets import QFileDialog, QMenu

from ..engine.core.errors import ForestregError
from ..engine.core.transform import apply as apply_transform
from .manual_panel import ComparisonView, TargetsPanel, next_target_id
from .tie_points import TIE_POINTS_PER_SCAN, TiePointsView
from .worker import TaskWorker, describe_error

log = logging.getLogger("forestreg")

TARGETS_FILTER = "Target lists (*.csv *.txt);;All files (*)"


class ManualModeMixin:
    """Targets, link methods, manual registration and the comparison (see the module docstring)."""

    # its signals (targetsChanged, reflectorsDetected, comparisonReady, comparisonFailed) are
    # declared on MainWindow: Qt signals belong to the QObject class

    # ================================================================== building

    def _build_manual(self) -> None:
        self.last_comparison: Optional[dict[str, Any]] = None
        self.targets_panel = TargetsPanel()
        self.comparison_view = ComparisonView()
        # tie points side by side: the reference and the moving scan next to the targets table
        self.tie_view = TiePointsView(renderer=self.scene_view.renderer)
        from PySide6.QtWidgets import QSplitter

        self.targets_tab = QSplitter(Qt.Orientation.Horizontal)
        # in scroll areas: their minimum heights must not make the results dock take half the window
        self.targets_tab.addWidget(_scrolled(self.targets_panel))
        self.targets_tab.addWidget(self.tie_view)
        self.targets_tab.setStretchFactor(0, 2)
        self.targets_tab.setStretchFactor(1, 5)
        self.comparison_tab = _scrolled(self.comparison_view)
        self.bottom_tabs.insertTab(2, self.targets_tab, "Targets")
        self.bottom_tabs.insertTab(3, self.comparison_tab, "Comparison")
        panel = self.targets_panel
        panel.targetsEdited.connect(self.set_targets)
        panel.editRejected.connect(lambda why: self.show_error("Cannot change the target", why))
        panel.scanChosen.connect(lambda name: self._show_targets(name))
        panel.pick_button.toggled.connect(self.set_pick_mode)
        panel.detect_button.clicked.connect(lambda: self.detect_reflectors())
        panel.import_button.clicked.connect(self._ask_import_targets)
        panel.export_button.clicked.connect(self._ask_export_targets)
        panel.manual_all_button.clicked.connect(lambda: self.set_all_link_methods("manual"))
        panel.run_manual_button.clicked.connect(lambda: self.run_manual())
        panel.compare_button.clicked.connect(lambda: self.compare_auto_manual())
        self.scene_view.pointPicked.connect(self._point_picked)
        self.tie_view.picked.connect(self._tie_picked)
        self.tie_view.pairChosen.connect(lambda ref, mov: self.show_tie_points(ref, mov))
        panel.table.itemSelectionChanged.connect(lambda: self.tie_view.highlight(panel.id_edit.text().strip()))
        panel.id_edit.textEdited.connect(lambda text: self.tie_view.highlight(text.strip()))
        self.bottom_tabs.currentChanged.connect(self._bottom_tab_changed)
        self.sceneReady.connect(self.draw_target_markers)
        self.link_table.setContextMenuPolicy(Qt.ContextMenuPolicy.CustomContextMenu)
        self.link_table.customContextMenuRequested.connect(self._link_table_menu)

        a = self._action
        self.act_import_targets = a(
            "&Import targets CSV\u2026",
            self._ask_import_targets,
            None,
            "Read target centres of the scans from a CSV (scan,target,x,y,z in each scan's file coordinates)",
        )
        self.act_export_targets = a(
            "&Export targets CSV\u2026", self._ask_export_targets, None, "Write the targets of every scan to a CSV"
        )
        self.act_detect = a(
            "&Detect reflectors",
            lambda: self.detect_reflectors(),
            None,
            "Find high-reflectance targets in the selected scan from its intensity",
        )
        self.act_pick = a(
            "&Pick target in 3D view",
            lambda: None,
            QKeySequenceText("Ctrl+T"),
            "Click a point of the selected scan in the 3D view to place the target named in the Targets tab",
            checkable=True,
        )
        self.act_pick.toggled.connect(self.set_pick_mode)
        self.act_all_manual = a(
            "Register all links from &targets (manual)",
            lambda: self.set_all_link_methods("manual"),
            None,
            "Set every link to the manual method",
        )
        self.act_all_auto = a(
            "Register all links from trunk &shadows (auto)",
            lambda: self.set_all_link_methods("auto"),
            None,
            "Set every link to the automatic (marker-free) method",
        )
        self.act_run_manual = a(
            "Run &manual registration",
            lambda: self.run_manual(),
            QKeySequenceText("Ctrl+M"),
            "Register the links set to manual from the scans' targets",
        )
        self.act_compare = a(
            "&Compare auto vs manual",
            lambda: self.compare_auto_manual(),
            None,
            "Register the plot both ways and show the paper's tables 4 and 5",
        )
        m = self.menuBar().addMenu("&Manual")
        for act in (
            self.act_import_targets,
            self.act_export_targets,
            None,
            self.act_detect,
            self.act_pick,
            None,
            self.act_all_manual,
            self.act_all_auto,
            self.act_run_manual,
            None,
            self.act_compare,
        ):
            if act is None:
                m.addSeparator()
            else:
                m.addAction(act)
        # keep Help last
        help_menu = next((x for x in self.menuBar().actions() if x.text() == "&Help"), None)
        if help_menu is not None:
            self.menuBar().removeAction(help_menu)
            self.menuBar().addAction(help_menu)

    # ================================================================== targets

    def _manual_refresh(self) -> None:
        """Show the project's scans and the chosen scan's targets (after any project change)."""
        if not hasattr(self, "targets_panel"):
            return
        names = [s.name for s in self.project.scans]
        self.targets_panel.set_scans(names)
        if not self.targets_panel.scan and names:
            self.targets_panel.select_scan(names[0])
        self._show_targets(self.targets_panel.scan)
        running = self.running
        for act in (
            self.act_import_targets,
            self.act_detect,
            self.act_all_manual,
            self.act_all_auto,
            self.act_run_manual,
            self.act_compare,
        ):
            act.setEnabled(not running and bool(names))
        for w in (
            self.targets_panel.detect_button,
            self.targets_panel.import_button,
            self.targets_panel.run_manual_button,
            self.targets_panel.compare_button,
            self.targets_panel.manual_all_button,
        ):
            w.setEnabled(not running and bool(names))

    def _show_targets(self, name: str) -> None:
        if not name:
            self.targets_panel.show_targets({}, "Add scans to list their targets.")
            return
        try:
            entry = self.project.scan(name)
        except KeyError:
            return
        links = [lk for lk in self.project.links if lk.moving == name and not lk.extra]
        method = links[0].method if links else ("centre" if name == self.project.centre else "auto")
        info = (
            f"{len(entry.targets)} target(s) of {name}, in its own file coordinates (m). "
            f"Its link: {method}. A manual link needs at least 3 targets shared (by id) with its reference scan."
        )
        self.targets_panel.show_targets(entry.targets, info)

    def targets_of(self, scan_name: str) -> dict[str, np.ndarray]:
        return dict(self.project.scan(scan_name).targets)

    def set_targets(self, scan_name: str, targets: Mapping[str, Any]) -> None:
        """Replace a scan's targets (file coordinates)."""
        self.project.scan(scan_name).targets = {
            str(k): np.asarray(v, dtype=float).reshape(3) for k, v in targets.items()
        }
        self._targets_changed(scan_name)

    def _targets_changed(self, scan_name: str) -> None:
        self.dirty = True
        self._update_title()
        if self.targets_panel.scan != scan_name:
            self.targets_panel.select_scan(scan_name)
        self._show_targets(scan_name)
        self.draw_target_markers()
        side = self.tie_view.side_of(scan_name)
        if side is not None:
            self.tie_view.set_targets(side, self.project.scan(scan_name).targets)
        self.targetsChanged.emit(scan_name)

    def add_picked_target(self, scan_name: str, target_id: Optional[str], xyz_file_coords: Any) -> str:
        """Add (or move) the target ``target_id`` of ``scan_name`` to a picked point, in that scan's
        file coordinates; with no id the one typed in the Targets tab (or the next free one) is
        used. Returns the id. The 3D view's pick callback calls this."""
        entry = self.project.scan(scan_name)
        tid = (target_id or "").strip() or self.targets_panel.id_edit.text().strip() or next_target_id(entry.targets)
        xyz = np.asarray(xyz_file_coords, dtype=float).reshape(3)
        if not np.isfinite(xyz).all():
            raise ValueError(f"the picked point {xyz_file_coords!r} is not finite")
        new = tid not in entry.targets
        entry.targets[tid] = xyz
        self._targets_changed(scan_name)
        if new:
            self.targets_panel.id_edit.setText(next_target_id(entry.targets))
        log.info("target %s of %s at %.3f %.3f %.3f", tid, scan_name, *xyz)
        self.statusBar().showMessage(f"Target {tid} of {scan_name} {'added' if new else 'moved'}", 5000)
        return tid

    def target_markers(self) -> np.ndarray:
        """Every scan's targets where the 3D view draws that scan (before: centred on its scanner;
        after: through its pose, centred on the centre scanner), (N, 3)."""
        scene = self.scene_view.scene
        if scene is None or not scene.clouds:
            return np.zeros((0, 3))
        drawn = {c.name for c in scene.clouds}
        out = []
        poses = self.project.poses() if scene.mode == "after" else {}
        origin = None
        if scene.mode == "after" and self.project.centre is not None:
            origin = np.asarray(self.scans(self.project.centre).scanner_position_file, dtype=float)
        for s in self.project.scans:
            if s.name not in drawn or not s.targets:
                continue
            pts = np.array([np.asarray(v, dtype=float).reshape(3) for v in s.targets.values()])
            if scene.mode == "before":
                pts = pts - np.asarray(self.scans(s.name).scanner_position_file, dtype=float)
            else:
                pose = poses.get(s.name)
                if pose is None:
                    continue
                pts = apply_transform(pose, pts) - (origin if origin is not None else 0.0)
            out.append(pts)
        return np.vstack(out) if out else np.zeros((0, 3))

    def draw_target_markers(self) -> None:
        try:
            self.scene_view.show_markers(self.target_markers())
        except Exception as exc:  # noqa: BLE001 - markers are a help, never fatal
            log.warning("the targets cannot be drawn: %s", exc)

    # ---------------------------------------------------------------- picking

    def set_pick_mode(self, on: bool) -> None:
        """Clicking a point of a scan in the 3D view places a target (the view shows the scans
        before registration, each in its own coordinates)."""
        on = bool(on)
        for w in (self.targets_panel.pick_button, self.act_pick):
            if w.isChecked() != on:
                w.blockSignals(True)
                w.setChecked(on)
                w.blockSignals(False)
        if on and self.scene_mode != "before":
            self.set_scene_mode("before")
        self.scene_view.set_pick_mode(on)
        self.tie_view.set_pick_mode(on)
        if on:
            self.bottom_tabs.setCurrentWidget(self.targets_tab)
            self.status_label.setText(
                "Pick target: click a point of a scan in the 3D view; it gets the id typed in the Targets tab"
            )

    def _point_picked(self, display_xyz: Any) -> None:
        """A point clicked in the 3D view (display coordinates of the before-view)."""
        found = self.scan_at(display_xyz)
        if found is None:
            return
        name, file_xyz = found
        try:
            self.add_picked_target(name, None, file_xyz)
        except (KeyError, ValueError) as exc:
            self.show_error("Cannot place the target", str(exc))

    # ---------------------------------------------------------------- tie points side by side

    def default_tie_pair(self) -> Optional[tuple[str, str]]:
        """(reference, moving): the scan in the Targets tab and its link's reference, else the
        first scan that is not the centre and its reference."""
        p = self.project
        if len(p.scans) < 2:
            return None
        chosen = self.targets_panel.scan
        names = [s.name for s in p.scans]
        moving = chosen if chosen in names and chosen != p.centre else next(n for n in names if n != p.centre)
        link = p.link_of(moving)
        reference = link.reference if link is not None else (p.centre or names[0])
        return reference, moving

    def show_tie_points(self, reference: Optional[str] = None, moving: Optional[str] = None) -> bool:
        """Draw ``reference`` and ``moving`` (default: :meth:`default_tie_pair`) side by side in the
        Targets tab, each with its targets. Returns False when there is no pair to show."""
        pair = self.default_tie_pair()
        if pair is None:
            return False
        reference, moving = reference or pair[0], moving or pair[1]
        names = [s.name for s in self.project.scans]
        self.tie_view.set_scans(names, reference, moving)
        colours = scan_colours_of(self.project)
        for side, name in (("reference", reference), ("moving", moving)):
            try:
                pts, scanner, total = self.previews.subset(self.project, name, TIE_POINTS_PER_SCAN)
            except (ForestregError, OSError, ValueError) as exc:
                log.warning("%s cannot be drawn: %s", name, exc)
                continue
            self.tie_view.show_side(
                side, name, pts, scanner, colours.get(name, "#777777"), total, self.project.scan(name).targets
            )
        self.tie_view.highlight(self.targets_panel.id_edit.text().strip() or None)
        return True

    def _bottom_tab_changed(self, _index: int) -> None:
        """The Targets tab needs room for its two 3D views: the results dock grows while it is shown."""
        on_targets = self.bottom_tabs.currentWidget() is self.targets_tab
        if on_targets and not self.tie_view.scanners:
            self.show_tie_points()
        height = max(320, int(self.height() * 0.5)) if on_targets else max(150, self.height() // 5)
        # after any pending layout pass (the first show sizes the dock too)
        QTimer.singleShot(0, lambda: self.resizeDocks([self.results_dock], [height], Qt.Orientation.Vertical))

    def _tie_picked(self, scan_name: str, file_xyz: Any) -> None:
        """A point picked in one of the side-by-side views: a target of that scan. The id stays
        in the Targets tab until the other scan of the pair has it too (pick it there next)."""
        try:
            tid = self.add_picked_target(scan_name, None, file_xyz)
        except (KeyError, ValueError) as exc:
            self.show_error("Cannot place the target", str(exc))
            return
        reference, moving = self.tie_view.pair
        other = moving if scan_name == reference else reference
        if other in [s.name for s in self.project.scans] and tid not in self.project.scan(other).targets:
            self.targets_panel.id_edit.setText(tid)
            self.status_label.setText(f"Target {tid} placed in {scan_name}: now pick {tid} in {other}")
        self.tie_view.highlight(tid)

    def scan_at(self, display_xyz: Any) -> Optional[tuple[str, np.ndarray]]:
        """The scan whose drawn point is nearest to a picked display point, and that point in the
        scan's file coordinates (before-view: each scan drawn centred on its scanner)."""
        scene = self.scene_view.scene
        if scene is None or scene.mode != "before" or not scene.clouds:
            return None
        p = np.asarray(display_xyz, dtype=float).reshape(3)
        best: Optional[tuple[float, str, np.ndarray]] = None
        chosen = self.targets_panel.scan
        for cloud in scene.clouds:
            if not len(cloud.points):
                continue
            d = np.linalg.norm(cloud.points - p, axis=1)
            k = int(np.argmin(d))
            dist = float(d[k]) - (1e-3 if cloud.name == chosen else 0.0)  # ties: the scan in the Targets tab
            if best is None or dist < best[0]:
                best = (dist, cloud.name, cloud.points[k].astype(float))
        if best is None:
            return None
        name = best[1]
        scanner = np.asarray(self.scans(name).scanner_position_file, dtype=float)
        return name, best[2] + scanner

    # ---------------------------------------------------------------- CSV

    def _ask_import_targets(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Import targets", self._last_dir(), TARGETS_FILTER)
        if path:
            self._remember_dir(path)
            self.import_targets_csv(path)

    def _ask_export_targets(self) -> None:
        path, _ = QFileDialog.getSaveFileName(
            self, "Export targets", str(Path(self._last_dir()) / "targets.csv"), TARGETS_FILTER
        )
        if path:
            self._remember_dir(path)
            self.export_targets_csv(path)

    def import_targets_csv(self, path: str | Path) -> int:
        """Read a target CSV (``engine.manual.read_targets_csv``) into the matching scans (by file
        name, stem or scan name); returns the number of targets read. Targets of a scan in the
        file replace that scan's targets with the same ids."""
        from ..app.targets import read_targets as read_targets_csv

        try:
            by_scan = read_targets_csv(path)
        except ForestregError as exc:
            self.show_error("Cannot read the targets", str(exc), describe_error(exc)[1])
            return 0
        lookup: dict[str, str] = {}
        for s in self.project.scans:
            for key in (s.name, Path(s.path).name, Path(s.path).stem, Path(s.name).stem):
                lookup.setdefault(key, s.name)
        count, unknown = 0, []
        for key, targets in by_scan.items():
            name = lookup.get(key) or lookup.get(Path(key).stem)
            if name is None:
                unknown.append(key)
                continue
            entry = self.project.scan(name)
            entry.targets.update({k: np.asarray(v, dtype=float) for k, v in targets.items()})
            count += len(targets)
        if unknown:
            self.show_error(
                "Some targets were not imported",
                f"The project has no scan named {', '.join(unknown)}; their targets were skipped.",
            )
        self.dirty = True
        self._update_title()
        self._manual_refresh()
        log.info("imported %d targets from %s", count, path)
        self.statusBar().showMessage(f"Imported {count} targets from {path}", 8000)
        return count

    def export_targets_csv(self, path: str | Path) -> bool:
        """Write every scan's targets (``engine.manual.write_targets_csv``, scan file names)."""
        from ..app.targets import write_targets as write_targets_csv

        data = {s.name: dict(s.targets) for s in self.project.scans if s.targets}
        try:
            write_targets_csv(path, data)
        except (ForestregError, OSError) as exc:
            message, details = describe_error(exc)
            self.show_error("Cannot write the targets", message, details)
            return False
        n = sum(len(v) for v in data.values())
        log.info("wrote %d targets to %s", n, path)
        self.statusBar().showMessage(f"Wrote {n} targets to {path}", 8000)
        return True

    # ---------------------------------------------------------------- reflectors

    def detect_reflectors(self, scan_name: Optional[str] = None, *, max_distance_m: float = 0.5) -> bool:
        """Find reflectors in a scan in the background (``engine.manual.detect_reflectors``). When
        the scan already has targets the detections are named after them
        (``match_detected_to_known`` within ``max_distance_m``); otherwise they are added as R1, R2..."""
        from ..app.targets import reflectors_in

        name = scan_name or self.targets_panel.scan
        if not name or self.running:
            return False
        scans, known = self.scans, self.targets_of(name)

        def work(progress: Any, cancel: Any) -> Any:
            progress(0.1, f"looking for reflectors in {name}")
            return reflectors_in(scans(name), known, max_distance_m)

        def done(result: Any) -> None:
            found, named = result
            entry = self.project.scan(name)
            if known:
                entry.targets.update(named)
                n = len(named)
                text = (
                    f"{len(found)} reflector(s) found in {name}; {n} of its {len(known)} targets moved to a detection"
                )
            else:
                added = {}
                k = 1
                for det in found:
                    while f"R{k}" in entry.targets:
                        k += 1
                    added[f"R{k}"] = np.asarray(det.centre, dtype=float)
                    entry.targets[f"R{k}"] = added[f"R{k}"]
                n = len(added)
                text = f"{n} reflector(s) found in {name}, added as R1\u2026" if n else f"No reflector found in {name}"
            self._targets_changed(name)
            self.status_label.setText(text)
            log.info("%s", text)
            self.reflectorsDetected.emit(name, n)

        self._start_task(
            TaskWorker(work, name="detect reflectors"),
            succeeded=done,
            failed=lambda m, d: self.show_error("Cannot detect reflectors", m, d),
        )
        return True

    # ================================================================== link methods

    def set_link_method(self, moving: str, method: str) -> None:
        """Register ``moving`` with ``method`` ("auto" or "manual") along its link (its result
        is forgotten); a scan without a link gets the default one first."""
        from ..app.plot import default_links

        if method not in ("auto", "manual"):
            raise ValueError(f"method must be 'auto' or 'manual', not {method!r}")
        p = self.project
        if moving == p.centre:
            raise ValueError(f"{moving} is the centre scan: it is not registered")
        default_links(p)
        link = p.link_of(moving)
        if link.method != method:
            p.set_link(
                moving,
                link.reference,
                method=method,
                vop_radius_m=link.vop_radius_m,
                slice_offsets_m=link.slice_offsets_m,
            )
        self.model._changed()

    def set_all_link_methods(self, method: str) -> None:
        from ..app.plot import default_links

        if self.running or not self.project.scans:
            return
        p = self.project
        default_links(p)
        for link in list(p.links):
            if not link.extra and link.method != method:
                p.set_link(
                    link.moving,
                    link.reference,
                    method=method,
                    vop_radius_m=link.vop_radius_m,
                    slice_offsets_m=link.slice_offsets_m,
                )
        self.model._changed()
        self.bottom_tabs.setCurrentWidget(self.link_table)

    def _link_method_actions(self, menu: QMenu, link: Any) -> None:
        if link.extra:
            return
        other = "manual" if link.method == "auto" else "auto"
        text = "Register from targets (manual)" if other == "manual" else "Register from trunk shadows (auto)"
        menu.addAction(text, lambda: self._edit(self.set_link_method, link.moving, other))
        menu.addAction(self.act_run_manual)

    def _link_table_menu(self, pos: QPoint) -> None:
        row = self.link_table.rowAt(pos.y())
        if row < 0 or self.running or row >= len(self.project.links):
            return
        menu = QMenu(self)
        self._link_method_actions(menu, self.project.links[row])
        menu.exec(self.link_table.viewport().mapToGlobal(pos))

    # ================================================================== running

    def run_manual(self) -> bool:
        """Run the links set to manual again (the other links keep their results)."""
        if self.running:
            return False
        manual = [link for link in self.project.links if link.method == "manual"]
        if not manual:
            self.show_error(
                "No manual link",
                "Set a link to manual first (right-click it in the Links table or the "
                "project tree, or Manual > Register all links from targets).",
            )
            return False
        short = []
        for link in manual:
            shared = set(self.project.scan(link.moving).targets) & set(self.project.scan(link.reference).targets)
            if len(shared) < 3:
                short.append(f"{link.moving} \u2192 {link.reference}: {len(shared)} shared target(s)")
        if short:
            log.warning("manual links with fewer than 3 shared targets will fail: %s", "; ".join(short))
        for link in manual:
            link.result = None
        self.project.adjustment = None
        return self.run()

    def _adopt_auto_results(self, work: Any) -> None:
        """Keep the automatic results the comparison computed for the window's auto links that had
        not been run (as the engine's ``compare_auto_manual`` keeps them in its project)."""
        taken = 0
        for link in self.project.links:
            if link.method != "auto" or link.extra or link.result is not None:
                continue
            done = work.link_of(link.moving)
            if done is not None and done.reference == link.reference and done.result is not None:
                link.result = copy.deepcopy(done.result)
                taken += 1
        if taken:
            self.model._changed()
            if any(p is not None for n, p in self.project.poses().items() if n != self.project.centre):
                self.set_scene_mode("after")

    def compare_auto_manual(self) -> bool:
        """Register the plot automatically and from the targets, in the background, on a copy of
        the project, and show the comparison. The window's project keeps its manual links as they
        are; its auto links that had not been run get the automatic results."""
        from ..app.comparison import compare_in_memory as compare_auto_manual
        from ..app.plot import Link

        if self.running or self.tasks.busy("compare") or len(self.project.scans) < 2:
            return False
        if not self.apply_panel_params():
            return False
        work = copy.deepcopy(self.project)
        work.path = None  # nothing is saved
        work.adjustment = None
        # the automatic side must run the marker-free method on every link
        for k, link in enumerate(work.links):
            if link.method != "auto":
                work.links[k] = Link(
                    moving=link.moving,
                    reference=link.reference,
                    method="auto",
                    vop_radius_m=link.vop_radius_m,
                    slice_offsets_m=link.slice_offsets_m,
                    extra=link.extra,
                )
        scans = self.scans
        self.status_label.setText("Comparing auto and manual registration\u2026")
        self.act_compare.setEnabled(False)
        self.targets_panel.compare_button.setEnabled(False)

        def done(result: Any) -> None:
            self._adopt_auto_results(work)
            self.last_comparison = result
            self.comparison_view.show_comparison(result)
            self.bottom_tabs.setCurrentWidget(self.comparison_tab)
            self.status_label.setText("Comparison ready (Comparison tab)")
            self.comparisonReady.emit(result)

        def failed(message: str, details: str) -> None:
            self.status_label.setText("Comparison failed")
            self.show_error("The comparison failed", message, details)
            self.comparisonFailed.emit(message, details)

        def ended() -> None:
            self.progress_bar.hide()
            self._manual_refresh()

        self._start_task(
            TaskWorker(
                lambda progress, cancel: compare_auto_manual(work, scans=scans, progress=progress, cancel=cancel),
                name="compare",
            ),
            succeeded=done,
            failed=failed,
            progress=self._show_progress,
            ended=ended,
        )
        return True


def scan_colours_of(project: Any) -> dict[str, str]:
    from ..engine.report.views import scan_colours

    return scan_colours(project)


def QKeySequenceText(text: str) -> Any:  # noqa: N802 - reads like the Qt class
    from PySide6.QtGui import QKeySequence

    return QKeySequence(text)


def _scrolled(widget: Any) -> Any:
    """``widget`` inside a frameless scroll area that resizes it."""
    from PySide6.QtWidgets import QFrame, QScrollArea

    area = QScrollArea()
    area.setWidgetResizable(True)
    area.setFrameShape(QFrame.Shape.NoFrame)
    area.setWidget(widget)
    return area
