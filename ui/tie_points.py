"""Tie points side by side: the reference and the moving scan of a link in two 3D views next to
each other, each in its own coordinates (centred on its scanner), with its targets drawn and
labelled. A point picked in either view becomes a target of that view's scan; one target id is
highlighted in both views, so the same target is found in the two scans one after the other.

This only shows and forwards picks: the window's manual mode (:mod:`forestreg.ui.manual_mode`)
keeps the targets in ``ScanEntry.targets`` (file coordinates) and registers from them.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QComboBox, QHBoxLayout, QLabel, QSplitter, QVBoxLayout, QWidget

from .scene_data import Scene, SceneCloud
from .scene_view import SceneView

#: Points drawn per scan in each of the two views.
TIE_POINTS_PER_SCAN = 80_000
TARGET_COLOUR = "#e0007a"
HIGHLIGHT_COLOUR = "#ffd400"
SIDES = ("reference", "moving")


class TiePointsView(QWidget):
    """Two 3D views (reference | moving). Emits :attr:`picked` (scan name, (3,) file coordinates)
    for a point clicked in either view in pick mode, and :attr:`pairChosen` (reference, moving)
    when the user chooses other scans."""

    picked = Signal(str, object)
    pairChosen = Signal(str, str)

    def __init__(self, parent: Optional[QWidget] = None, renderer: Optional[str] = None) -> None:
        super().__init__(parent)
        self.combos: dict[str, QComboBox] = {}
        self.views: dict[str, SceneView] = {}
        self.captions: dict[str, QLabel] = {}
        self.scanners: dict[str, np.ndarray] = {}  # side -> scanner (file coordinates)
        self.targets: dict[str, dict[str, np.ndarray]] = {"reference": {}, "moving": {}}
        self.highlighted: Optional[str] = None
        self._loading = False
        split = QSplitter(Qt.Orientation.Horizontal)
        for side in SIDES:
            box = QWidget()
            lay = QVBoxLayout(box)
            lay.setContentsMargins(0, 0, 0, 0)
            row = QHBoxLayout()
            row.addWidget(QLabel("Reference scan:" if side == "reference" else "Moving scan:"))
            combo = QComboBox()
            combo.setToolTip(f"The {side} scan drawn in this view (in its own coordinates, centred on its scanner)")
            combo.currentTextChanged.connect(self._combo_changed)
            row.addWidget(combo, 1)
            lay.addLayout(row)
            view = SceneView(renderer=renderer)
            view.setMinimumSize(160, 120)
            view.pointPicked.connect(lambda p, s=side: self.pick(s, p))
            lay.addWidget(view, 1)
            caption = QLabel("")
            caption.setStyleSheet("color: #555;")
            lay.addWidget(caption)
            split.addWidget(box)
            self.combos[side], self.views[side], self.captions[side] = combo, view, caption
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(split, 1)

    # ------------------------------------------------------------------ choosing scans

    def set_scans(self, names: list[str], reference: str, moving: str) -> None:
        """The scans to choose from and the pair shown (no signal)."""
        self._loading = True
        try:
            for side, chosen in (("reference", reference), ("moving", moving)):
                combo = self.combos[side]
                if [combo.itemText(k) for k in range(combo.count())] != names:
                    combo.clear()
                    combo.addItems(names)
                combo.setCurrentText(chosen)
        finally:
            self._loading = False

    @property
    def pair(self) -> tuple[str, str]:
        return self.combos["reference"].currentText(), self.combos["moving"].currentText()

    def side_of(self, scan_name: str) -> Optional[str]:
        return next((s for s in SIDES if self.combos[s].currentText() == scan_name), None)

    def _combo_changed(self, _text: str) -> None:
        if not self._loading:
            self.pairChosen.emit(*self.pair)

    # ------------------------------------------------------------------ drawing

    def show_side(
        self,
        side: str,
        name: str,
        points_file: np.ndarray,
        scanner_file: np.ndarray,
        colour: str,
        total: int,
        targets: Mapping[str, Any],
    ) -> None:
        """Draw one scan (file coordinates in, drawn centred on its scanner) and its targets."""
        scanner = np.asarray(scanner_file, dtype=float).reshape(3)
        self.scanners[side] = scanner
        cloud = SceneCloud(
            name, (np.asarray(points_file, dtype=float) - scanner).astype(np.float32), colour, np.zeros(3), int(total)
        )
        self.views[side].show_scene(Scene(mode="before", clouds=[cloud]))
        self.set_targets(side, targets)

    def set_targets(self, side: str, targets: Mapping[str, Any]) -> None:
        self.targets[side] = {str(k): np.asarray(v, dtype=float).reshape(3) for k, v in targets.items()}
        self._draw_targets(side)

    def highlight(self, target_id: Optional[str]) -> None:
        """Draw ``target_id`` larger and yellow in both views (None: no highlight)."""
        self.highlighted = target_id or None
        for side in SIDES:
            self._draw_targets(side)

    def _draw_targets(self, side: str) -> None:
        import pyvista as pv

        view = self.views[side]
        pl = view.plotter
        if pl is None or side not in self.scanners:
            return
        targets = self.targets[side]
        display = {k: v - self.scanners[side] for k, v in targets.items()}
        view.show_markers(np.array(list(display.values())) if display else np.zeros((0, 3)), colour=TARGET_COLOUR)
        for name in ("target-labels", "target-highlight", "target-highlight-label"):
            try:
                pl.remove_actor(name, render=False)
            except Exception:  # noqa: BLE001 - nothing drawn yet
                pass
        if display and view.scene is not None:
            others = [k for k in display if k != self.highlighted]
            if others:
                pl.add_point_labels(
                    np.array([display[k] for k in others]),
                    others,
                    name="target-labels",
                    font_size=11,
                    point_size=1,
                    shape_opacity=0.6,
                    always_visible=True,
                    pickable=False,
                    reset_camera=False,
                )
            if self.highlighted in display:
                at = display[self.highlighted][None, :].astype(np.float32)
                pl.add_mesh(
                    pv.PolyData(at),
                    color=HIGHLIGHT_COLOUR,
                    point_size=22,
                    style="points",
                    render_points_as_spheres=True,
                    name="target-highlight",
                    reset_camera=False,
                    pickable=False,
                )
                pl.add_point_labels(
                    at,
                    [self.highlighted],
                    name="target-highlight-label",
                    font_size=14,
                    bold=True,
                    text_color="black",
                    shape_color=HIGHLIGHT_COLOUR,
                    shape_opacity=0.95,
                    point_size=1,
                    always_visible=True,
                    pickable=False,
                    reset_camera=False,
                )
        name = self.combos[side].currentText()
        here = (
            f"target {self.highlighted} " + ("placed" if self.highlighted in targets else "not placed yet")
            if self.highlighted
            else ""
        )
        self.captions[side].setText(f"{name}: {len(targets)} target(s)" + (f"; {here}" if here else ""))
        view._update()

    # ------------------------------------------------------------------ picking

    def set_pick_mode(self, on: bool) -> None:
        for view in self.views.values():
            view.set_pick_mode(on)

    def pick(self, side: str, display_xyz: Any) -> None:
        """A point picked in one view (display coordinates: that scan's file coordinates minus its
        scanner): emits :attr:`picked` with the scan and the point in its file coordinates."""
        if side not in self.scanners:
            return
        p = np.asarray(display_xyz, dtype=float).reshape(3)
        if np.isfinite(p).all():
            self.picked.emit(self.combos[side].currentText(), p + self.scanners[side])

    def close_views(self) -> None:
        for view in self.views.values():
            view.close_view()
