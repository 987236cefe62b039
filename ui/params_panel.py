"""The parameter panel, built from the engine's parameter metadata (:func:`parameter_table`).

One editor per field of :class:`~forestreg.engine.tls.params.RegistrationParams` (the fields of a
nested set, such as its ICP settings, under a heading of their own): a spin box with its
unit, range and help as tooltip for numbers, a check box for switches, comma-separated text for
lists of heights or distances, and "auto" for an optional value (the VOP radius). The panel never
judges values itself: :meth:`ParameterPanel.params` builds a ``RegistrationParams`` and the
engine's validation decides; an invalid entry is shown in red with the engine's message.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QDoubleSpinBox,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QPushButton,
    QScrollArea,
    QSpinBox,
    QStyle,
    QVBoxLayout,
    QWidget,
)

from ..engine.core.errors import ForestregError, ParameterError
from ..engine.core.params import parameter_table
from ..engine.params import load_params
from ..engine.tls.params import RegistrationParams

#: Units shown after a value (the metadata's short forms spelt out where useful).
UNIT_SUFFIX = {"m": " m", "deg": "\u00b0", "points": " points", "VOPs": " VOPs", "1": ""}  # "1": dimensionless
#: Largest value a spin box offers where the metadata gives no upper bound.
UNBOUNDED = 1.0e6


#: Plain words for the parameters whose name is paper jargon; the paper's symbol goes to the tooltip.
PLAIN_LABELS = {
    "max_range_m": "Keep points within",
    "ground_voxel_m": "Ground search cell",
    "slice_thickness_m": "Slice thickness",
    "slice_offsets_m": "Slice heights",
    "fallback_slice_offsets_m": "Extra slice heights",
    "follow_terrain": "Slice follows terrain",
    "angular_step_deg": "Angle step",
    "radial_step_m": "Distance step",
    "vop_radius_m": "Trunk-shadow radius",
    "visibility_gap_m": "Gap behind a trunk",
    "component_voxel_m": "Trunk search cell",
    "min_component_points": "Trunk: fewest points",
    "min_component_height_fraction": "Trunk: least height share",
    "max_component_width_m": "Trunk: widest",
    "mean_shift_bandwidth_m": "Trunk centre search",
    "centre_on_trunk_axis": "Shadows on trunk axis",
    "match_distance_m": "Match distance",
    "min_vops": "Fewest shadows per scan",
    "min_matched": "Fewest matched shadows",
    "margin": "Lead over runner-up",
    "margin.min_lead": "Lead over runner-up",
    "margin.min_lead_fraction": "Lead over runner-up (share)",
    "distinct": "Distinct solutions",
    "distinct.rotation_deg": "Distinct if turned by",
    "distinct.translation_m": "Distinct if moved by",
    "max_free_space_violation": "Most points in seen-empty space",
    "level_tilted": "Level tilted scanners",
    "tilt_threshold_deg": "Ignore tilts below",
    "icp": "Fine fit",
    "icp.voxel_m": "Fine fit cell",
    "icp.max_distances_m": "Fine fit distances",
    "icp.iterations": "Fine fit iterations",
    "icp_min_fitness": "Fine fit: least overlap",
    "icp_max_correction_m": "Fine fit: largest change",
}


def label_for(name: str, paper: str = "") -> str:
    """A label in plain words: ``max_range_m`` -> "Keep points within". The paper's symbol
    (``paper``, e.g. "D_c = 30 m") is not part of the label: it goes to the tooltip. A field of a
    nested set (``icp.normal_neighbours``) is labelled after its set: "Fine fit: normal neighbours"."""
    if name in PLAIN_LABELS:
        return PLAIN_LABELS[name]
    if "." in name:
        group, rest = name.rsplit(".", 1)
        return f"{label_for(group)}: {label_for(rest).lower()}"
    words = name.split("_")
    if words and words[-1] in ("m", "deg"):
        words = words[:-1]
    text = " ".join(words).capitalize()
    for jargon, plain in (
        ("Icp", "Fine registration"),
        ("icp", "fine registration"),
        ("Vops", "Trunk shadows"),
        ("vops", "trunk shadows"),
        ("Vop", "Trunk-shadow"),
        ("vop", "trunk-shadow"),
    ):
        text = text.replace(jargon, plain)
    return text


def format_tuple(values: Any) -> str:
    """``(0.5, 0.2)`` -> "0.5, 0.2"."""
    return ", ".join(f"{float(v):g}" for v in (values or ()))


def parse_tuple(text: str) -> tuple[float, ...]:
    """ "0.5, 0.2" -> ``(0.5, 0.2)`` (semicolons and spaces also separate); raises ParameterError."""
    parts = [t for t in text.replace(";", ",").replace(" ", ",").split(",") if t.strip()]
    try:
        return tuple(float(t) for t in parts)
    except ValueError as exc:
        raise ParameterError(f"'{text}' is not a list of numbers separated by commas") from exc


def _decimals(lo: Optional[float], default: Any) -> int:
    smallest = (
        min(abs(v) for v in (lo, default) if isinstance(v, (int, float)) and v)
        if any(isinstance(v, (int, float)) and v for v in (lo, default))
        else 1.0
    )
    return int(min(6, max(2, math.ceil(-math.log10(smallest)) + 1)))


class _Field:
    """One editor and how to read and write its value."""

    def __init__(self, row: dict[str, Any], panel: "ParameterPanel") -> None:
        self.name: str = row["name"]
        self.default = row["default"]
        self.unit: str = row["unit"] or ""
        lo, hi = row["range"] or (None, None)
        tip = [f"{label_for(self.name)}: {row['help']}"]
        if lo is not None or hi is not None:
            tip.append(
                f"Range: {lo if lo is not None else '-inf'} to {hi if hi is not None else 'inf'} {self.unit}".rstrip()
            )
        if row["paper"]:
            tip.append(f"Paper's symbol: {row['paper']}")
        tip.append(f"Default: {self._text(self.default)}   (name: {self.name})")
        self.tooltip = "\n".join(tip)
        self.auto: Optional[QCheckBox] = None
        if isinstance(self.default, bool):
            self.kind = "bool"
            self.editor: QWidget = QCheckBox()
            self.editor.toggled.connect(panel._edited)
        elif isinstance(self.default, tuple):
            self.kind = "tuple"
            self.editor = QLineEdit()
            self.editor.setPlaceholderText("none" if self.name.startswith("fallback") else "comma-separated")
            self.editor.textChanged.connect(panel._edited)
        elif isinstance(self.default, int):
            self.kind = "int"
            box = QSpinBox()
            box.setRange(int(lo if lo is not None else 0), int(min(hi if hi is not None else UNBOUNDED, 2**31 - 1)))
            box.setSuffix(UNIT_SUFFIX.get(self.unit, f" {self.unit}" if self.unit else ""))
            box.valueChanged.connect(panel._edited)
            self.editor = box
        else:
            self.kind = "float" if self.default is not None else "optional"
            box = QDoubleSpinBox()
            box.setDecimals(_decimals(lo, self.default))
            box.setRange(float(lo if lo is not None else 0.0), float(hi if hi is not None else UNBOUNDED))
            box.setSingleStep(_step(lo, hi, self.default))
            box.setSuffix(UNIT_SUFFIX.get(self.unit, f" {self.unit}" if self.unit else ""))
            box.valueChanged.connect(panel._edited)
            self.editor = box
            if self.kind == "optional":
                self.auto = QCheckBox("auto")
                self.auto.setToolTip(
                    "Let the engine choose per scan (it tries increasing values); untick to set a value"
                )
                # while "auto" is on no number is shown: a greyed value would read as the one in use
                self.auto_note = QLabel("per scan")
                self.auto_note.setStyleSheet("color: #667085;")
                self.auto.toggled.connect(lambda on: (box.setVisible(not on), self.auto_note.setVisible(on)))
                self.auto.toggled.connect(panel._edited)
        self.editor.setToolTip(self.tooltip)
        self.editor.setObjectName(f"param_{self.name}")

    @staticmethod
    def _text(value: Any) -> str:
        if value is None:
            return "auto"
        if isinstance(value, tuple):
            return format_tuple(value) or "none"
        return str(value)

    def widget(self) -> QWidget:
        if self.auto is None:
            return self.editor
        holder = QWidget()
        lay = QHBoxLayout(holder)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.auto)
        lay.addWidget(self.editor, 1)
        lay.addWidget(self.auto_note, 1)
        on = self.auto.isChecked()
        self.editor.setVisible(not on)
        self.auto_note.setVisible(on)
        return holder

    def set(self, value: Any) -> None:
        if self.kind == "bool":
            self.editor.setChecked(bool(value))
        elif self.kind == "tuple":
            self.editor.setText(format_tuple(value))
        elif self.kind == "int":
            self.editor.setValue(int(value))
        elif self.kind == "optional":
            self.auto.setChecked(value is None)
            if value is not None:
                self.editor.setValue(float(value))
        else:
            self.editor.setValue(float(value))

    def get(self) -> Any:
        if self.kind == "bool":
            return self.editor.isChecked()
        if self.kind == "tuple":
            return parse_tuple(self.editor.text())
        if self.kind == "int":
            return int(self.editor.value())
        if self.kind == "optional" and self.auto.isChecked():
            return None
        return float(self.editor.value())

    def mark(self, bad: bool) -> None:
        self.editor.setStyleSheet("background: #fde2e1;" if bad else "")


def _step(lo: Optional[float], hi: Optional[float], default: Any) -> float:
    ref = default if isinstance(default, (int, float)) and default else (lo or 1.0)
    return float(10 ** math.floor(math.log10(abs(ref)))) if ref else 0.1


class ParameterPanel(QWidget):
    """Editors for every registration parameter; emits :attr:`paramsChanged` with a valid
    ``RegistrationParams`` after each edit that the engine accepts."""

    paramsChanged = Signal(object)

    def __init__(self, parent: Optional[QWidget] = None) -> None:
        super().__init__(parent)
        self._fields: dict[str, _Field] = {}
        self._loading = False
        outer = QVBoxLayout(self)
        outer.setContentsMargins(4, 4, 4, 4)
        self.message = QLabel("")
        self.message.setWordWrap(True)
        self.message.setStyleSheet("color: #b42318;")
        self.message.hide()
        outer.addWidget(self.message)
        area = QScrollArea()
        area.setWidgetResizable(True)
        area.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        inner = QWidget()
        form = QFormLayout(inner)
        # room between the spin boxes' arrows and the scroll bar
        form.setContentsMargins(4, 4, 4 + area.style().pixelMetric(QStyle.PixelMetric.PM_ScrollBarExtent) // 2, 4)
        form.setFieldGrowthPolicy(QFormLayout.FieldGrowthPolicy.AllNonFixedFieldsGrow)
        group = ""
        for row in parameter_table(RegistrationParams):
            f = _Field(row, self)
            self._fields[f.name] = f
            if f.name.rpartition(".")[0] != group:  # a nested set begins (or ends)
                group = f.name.rpartition(".")[0]
                if group:
                    heading = QLabel(f"<b>{label_for(group)}</b>")
                    heading.setToolTip(f"The settings of [registration.{group}] in a parameter file")
                    form.addRow(heading)
            label = QLabel(label_for(f.name, row["paper"]))
            label.setToolTip(f.tooltip)
            form.addRow(label, f.widget())
        area.setWidget(inner)
        outer.addWidget(area, 1)
        buttons = QHBoxLayout()
        self.reset_button = QPushButton("Defaults")
        self.reset_button.setToolTip("Set every parameter to the paper's / forestreg's default")
        self.reset_button.clicked.connect(lambda: self.set_params(RegistrationParams(), emit=True))
        buttons.addWidget(self.reset_button)
        self.load_button = QPushButton("Load\u2026")
        self.load_button.setToolTip("Read parameters from a TOML file ([registration] table)")
        buttons.addWidget(self.load_button)
        buttons.addStretch(1)
        outer.addLayout(buttons)
        self.set_params(RegistrationParams())

    # ------------------------------------------------------------------ values

    def field_names(self) -> list[str]:
        return list(self._fields)

    def editor(self, name: str) -> QWidget:
        """The editor of one parameter (for tests and focus)."""
        return self._fields[name].editor

    def set_value(self, name: str, value: Any) -> None:
        """Set one editor as a user would (emits paramsChanged when the result is valid)."""
        self._fields[name].set(value)

    def set_params(self, params: RegistrationParams, *, emit: bool = False) -> None:
        """Show ``params`` in the editors."""
        self._loading = True
        try:
            for name, f in self._fields.items():
                value: Any = params
                for part in name.split("."):
                    value = getattr(value, part)
                f.set(value)
                f.mark(False)
        finally:
            self._loading = False
        self.message.hide()
        if emit:
            self.paramsChanged.emit(params)

    def params(self) -> RegistrationParams:
        """The parameters as edited; raises :class:`ParameterError` with the engine's reason."""
        values: dict[str, Any] = {}
        for name, f in self._fields.items():
            *groups, last = name.split(".")
            table = values
            for g in groups:  # a nested set's fields go into its own table
                table = table.setdefault(g, {})
            try:
                table[last] = f.get()
            except ParameterError as exc:
                raise ParameterError(f"{label_for(name)}: {exc}") from exc
        return RegistrationParams.from_mapping(values)

    def load_toml(self, path: str | Path) -> RegistrationParams:
        """Read a parameter file into the editors (raises ParameterError)."""
        params = load_params(path).registration
        self.set_params(params, emit=True)
        return params

    def _edited(self, *_: Any) -> None:
        if self._loading:
            return
        for f in self._fields.values():
            f.mark(False)
        try:
            params = self.params()
        except ForestregError as exc:
            text = str(exc)
            for name, f in self._fields.items():
                group, _, last = name.rpartition(".")
                if (
                    text.startswith(name)
                    or text.startswith(label_for(name))
                    or f"({name}" in text
                    or (group and f"[{group}] {last}" in text)
                ):
                    f.mark(True)
            self.message.setText(text)
            self.message.show()
            return
        self.message.hide()
        self.paramsChanged.emit(params)
