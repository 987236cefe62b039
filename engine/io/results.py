"""Readers for the result folders of System B: ``forestreg trees --out DIR`` and ``forestreg
coregister --out DIR`` (the desktop, scripts and tests read them here instead of parsing CSV or
JSON themselves).

* :func:`read_trees_dir`: ``trees.csv`` (columns found by name; columns this reader does not know,
  e.g. per-measure quality figures added later, are kept in :attr:`TreeRow.extra`),
  ``stem_curves.csv`` and ``cylinders/tree_NNNN.csv``.
* :func:`read_coregistration_dir`: ``result.json``, ``keypoints_ground.csv``, ``keypoints_uav.csv``.

Frames: everything is in file coordinates, as written (metres).
"""

from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import numpy as np

from ..core.errors import ScanReadError

__all__ = [
    "CoregistrationOutput",
    "StemCurveRows",
    "TreeRow",
    "TreesOutput",
    "read_coregistration_dir",
    "read_csv_rows",
    "read_trees_dir",
    "trees_output_from_inventory",
]

PathLike = Union[str, os.PathLike[str]]

#: Columns of trees.csv read as text (everything else is a number; empty cells are NaN).
TEXT_COLUMNS = ("flag", "flags", "edited", "edit", "tree_id", "species", "source", "dbh_quality", "height_quality", "crown_quality", "volume_quality")


def read_csv_rows(path: PathLike) -> tuple[list[str], list[dict[str, str]]]:
    """Header and rows (dicts by column name) of a CSV file; :class:`ScanReadError` if unreadable."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader)
            return list(reader.fieldnames or []), rows
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ScanReadError(f"cannot read {path}: {exc}") from exc


def _number(text: Any) -> float:
    if text is None:
        return math.nan
    t = str(text).strip()
    if not t:
        return math.nan
    try:
        return float(t)
    except ValueError:
        return math.nan


@dataclass(frozen=True)
class TreeRow:
    """One row of ``trees.csv``: the id, its position, every numeric measure by column name
    (``values``, NaN where empty), the flag text ("" = complete and measured) and any other text
    column (``extra``)."""

    tree_id: int
    x: float
    y: float
    z: float
    values: Mapping[str, float]
    flag: str = ""
    extra: Mapping[str, str] = field(default_factory=dict)

    def get(self, name: str) -> float:
        """A measure by column name (NaN if the table has no such column or the cell is empty)."""
        return float(self.values.get(name, math.nan))

    @property
    def flagged(self) -> bool:
        return bool(self.flag.strip())

    @property
    def edited(self) -> str:
        """The edit note of a tree changed by hand ("" if none)."""
        return str(self.extra.get("edited", "") or self.extra.get("edit", "")).strip()


@dataclass(frozen=True)
class StemCurveRows:
    """One tree's stem curve: heights above ground (m), diameters (m, NaN where none), centres
    (K, 3; file coordinates) and whether each diameter was accepted or interpolated."""

    height_m: np.ndarray
    diameter_m: np.ndarray
    raw_diameter_m: np.ndarray
    centres: np.ndarray
    accepted: np.ndarray
    interpolated: np.ndarray
    reasons: tuple[str, ...]


@dataclass(frozen=True)
class TreesOutput:
    """A ``forestreg trees --out DIR`` folder."""

    folder: Path
    columns: tuple[str, ...]
    trees: list[TreeRow]
    curves: dict[int, StemCurveRows]
    cylinder_files: dict[int, Path]
    #: cylinder models held in memory (an inventory measured or edited in this session)
    models: Mapping[int, Any] = field(default_factory=dict)

    def tree(self, tree_id: int) -> TreeRow:
        for t in self.trees:
            if t.tree_id == tree_id:
                return t
        raise KeyError(tree_id)

    def cylinders(self, tree_id: int) -> Any:
        """The tree's :class:`~forestreg.engine.trees.qsm.CylinderModel`, or None without one."""
        from ..trees.qsm import CylinderModel

        if int(tree_id) in self.models:
            return self.models[int(tree_id)]
        path = self.cylinder_files.get(int(tree_id))
        return CylinderModel.read_csv(path) if path is not None else None

    @property
    def numeric_columns(self) -> tuple[str, ...]:
        return tuple(c for c in self.columns if c not in TEXT_COLUMNS)


def read_trees_dir(folder: PathLike) -> TreesOutput:
    """Read a trees result folder (see the module docstring).

    Raises :class:`ScanReadError` when the folder has no readable ``trees.csv`` or the table lacks
    ``tree_id``, ``x`` or ``y``; a missing ``stem_curves.csv`` or cylinder folder gives empty ones.
    """
    root = Path(folder)
    table = root / "trees.csv"
    if not table.is_file():
        raise ScanReadError(f"{root} is not a trees result folder (no trees.csv; made by 'forestreg trees --out DIR')")
    header, rows = read_csv_rows(table)
    missing = [c for c in ("tree_id", "x", "y") if c not in header]
    if missing:
        raise ScanReadError(f"{table}: not a tree table, missing column(s) {', '.join(missing)}")
    trees: list[TreeRow] = []
    for k, r in enumerate(rows):
        tid = _number(r.get("tree_id"))
        if not math.isfinite(tid):
            raise ScanReadError(f"{table}: line {k + 2} has no tree id")
        values = {c: _number(r.get(c)) for c in header if c not in TEXT_COLUMNS}
        extra = {c: str(r.get(c) or "") for c in header if c in TEXT_COLUMNS and c not in ("flag", "tree_id")}
        trees.append(TreeRow(tree_id=int(tid), x=values.get("x", math.nan), y=values.get("y", math.nan),
                             z=values.get("z", math.nan), values=values, flag=str(r.get("flag") or ""), extra=extra))
    curves: dict[int, StemCurveRows] = {}
    curve_file = root / "stem_curves.csv"
    if curve_file.is_file():
        _, crow = read_csv_rows(curve_file)
        grouped: dict[int, list[dict[str, str]]] = {}
        for r in crow:
            tid = _number(r.get("tree_id"))
            if math.isfinite(tid):
                grouped.setdefault(int(tid), []).append(r)
        for tid, rs in grouped.items():
            rs.sort(key=lambda r: _number(r.get("height_m")))
            curves[tid] = StemCurveRows(
                height_m=np.array([_number(r.get("height_m")) for r in rs]),
                diameter_m=np.array([_number(r.get("diameter_m")) for r in rs]),
                raw_diameter_m=np.array([_number(r.get("raw_diameter_m")) for r in rs]),
                centres=np.array([[_number(r.get(c)) for c in ("x", "y", "z")] for r in rs]).reshape(-1, 3),
                accepted=np.array([_number(r.get("accepted")) == 1 for r in rs], dtype=bool),
                interpolated=np.array([_number(r.get("interpolated")) == 1 for r in rs], dtype=bool),
                reasons=tuple(str(r.get("reason") or "") for r in rs),
            )
    cylinder_files: dict[int, Path] = {}
    cyl_dir = root / "cylinders"
    if cyl_dir.is_dir():
        for path in sorted(cyl_dir.glob("tree_*.csv")):
            try:
                cylinder_files[int(path.stem.split("_", 1)[1])] = path
            except ValueError:
                continue
    return TreesOutput(folder=root, columns=tuple(header), trees=trees, curves=curves, cylinder_files=cylinder_files)


def trees_output_from_inventory(inventory: Any, notes: Optional[Mapping[int, str]] = None, folder: PathLike = "") -> TreesOutput:
    """The same view of an in-memory :class:`~forestreg.engine.trees.inventory.TreeInventory`
    (file coordinates, as ``trees.csv`` would hold them); ``notes`` tree id -> edit note."""
    import dataclasses

    from ..trees.inventory import TREE_COLUMNS

    shift = np.asarray(inventory.origin_shift, dtype=np.float64)
    notes = dict(notes or {})
    trees, curves, models = [], {}, {}
    for rec in inventory.trees:
        row = rec.row(shift)
        values = {c: float(row[c]) for c in TREE_COLUMNS if c not in TEXT_COLUMNS and c in row}
        extra = {"edited": notes[rec.tree_id]} if notes.get(rec.tree_id) else {}
        trees.append(TreeRow(tree_id=int(rec.tree_id), x=values["x"], y=values["y"], z=values["z"], values=values,
                             flag=str(row.get("flag") or ""), extra=extra))
        c = rec.curve
        curves[int(rec.tree_id)] = StemCurveRows(
            height_m=np.asarray(c.heights_m, dtype=float), diameter_m=np.asarray(c.diameter_m, dtype=float),
            raw_diameter_m=np.asarray(c.raw_diameter_m, dtype=float), centres=np.asarray(c.centres, dtype=float) + shift,
            accepted=np.asarray(c.accepted, dtype=bool), interpolated=np.asarray(c.interpolated, dtype=bool),
            reasons=tuple(c.reasons))
        if rec.cylinders is not None:
            models[int(rec.tree_id)] = dataclasses.replace(rec.cylinders, start=rec.cylinders.start + shift)
    columns = tuple(TREE_COLUMNS) + (("edited",) if notes else ())
    return TreesOutput(folder=Path(folder), columns=columns, trees=trees, curves=curves, cylinder_files={}, models=models)


@dataclass(frozen=True)
class CoregistrationOutput:
    """A ``forestreg coregister --out DIR`` folder: ``result`` (result.json as written), the 4x4
    matrix (None when it failed) and the keypoints of each cloud (K, 3; file coordinates) with,
    per keypoint, the index of its match in the other cloud (-1 = unmatched)."""

    folder: Path
    result: Mapping[str, Any]
    matrix: Optional[np.ndarray]
    ground_keypoints: np.ndarray
    ground_matched: np.ndarray
    uav_keypoints: np.ndarray
    uav_matched: np.ndarray

    @property
    def ok(self) -> bool:
        return self.result.get("status") == "ok" and self.matrix is not None

    @property
    def reason(self) -> str:
        return str(self.result.get("reason") or "")

    @property
    def figure(self) -> Optional[Path]:
        """The report's figure (a PNG) if the folder has one."""
        pngs = sorted(self.folder.glob("*.png"))
        return pngs[0] if pngs else None

    @property
    def report(self) -> Optional[Path]:
        path = self.folder / "report.html"
        return path if path.is_file() else None


def _keypoints(path: Path) -> tuple[np.ndarray, np.ndarray]:
    if not path.is_file():
        return np.zeros((0, 3)), np.zeros(0, dtype=int)
    header, rows = read_csv_rows(path)
    xyz = np.array([[_number(r.get(c)) for c in ("x", "y", "z")] for r in rows], dtype=np.float64).reshape(-1, 3)
    key = next((c for c in ("matched_with", "matched", "match") if c in header), None)
    matched = np.array([int(_number(r.get(key))) if key and math.isfinite(_number(r.get(key))) else -1 for r in rows],
                       dtype=int)
    return xyz, matched


def read_coregistration_dir(folder: PathLike) -> CoregistrationOutput:
    """Read a co-registration result folder; :class:`ScanReadError` without a readable result.json."""
    root = Path(folder)
    path = root / "result.json"
    if not path.is_file():
        raise ScanReadError(f"{root} is not a co-registration result folder (no result.json; made by 'forestreg coregister --out DIR')")
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ScanReadError(f"cannot read {path}: {exc}") from exc
    if not isinstance(result, dict):
        raise ScanReadError(f"{path}: not a co-registration result")
    m = result.get("matrix")
    matrix = None
    if m is not None:
        try:
            matrix = np.asarray(m, dtype=np.float64).reshape(4, 4)
        except (ValueError, TypeError) as exc:
            raise ScanReadError(f"{path}: the matrix is not 4x4 ({exc})") from exc
    g, gm = _keypoints(root / "keypoints_ground.csv")
    u, um = _keypoints(root / "keypoints_uav.csv")
    return CoregistrationOutput(folder=root, result=result, matrix=matrix, ground_keypoints=g, ground_matched=gm,
                                uav_keypoints=u, uav_matched=um)
