"""Readers and writers of the tabular output files shared by several use cases (not every output
format: ``result.json``, the reports, the point clouds and the change folder are written by their
own use cases and writers).

Written here: the trees tables (``trees.csv``, ``stem_curves.csv``, ``cylinders/tree_NNNN.csv``)
and the hand edits (``edits.json``), ``poses.json`` with the ``*.transform.txt`` files, the
comparison (JSON and CSV), the targets CSV, the project file (:class:`ProjectFile`) and the
evaluation tables. Read here: the trees folder and the co-registration folder. The writers take
plain data or any object with the attributes they name (this module imports no domain package);
the desktop, scripts and tests read the folders here instead of parsing CSV or JSON themselves.

* :func:`read_trees_dir`: ``trees.csv`` (columns found by name; columns this reader does not know,
  e.g. per-measure quality figures added later, are kept in :attr:`TreeRow.extra`),
  ``stem_curves.csv`` and ``cylinders/tree_NNNN.csv``.
* :func:`read_coregistration_dir`: ``result.json``, ``keypoints_ground.csv``, ``keypoints_uav.csv``.

Frames: everything is in file coordinates, as written (metres).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from ..core.atomic import write_text_atomic
from ..core.errors import ProjectFileError, ScanReadError, TargetError
from ..core.jsonable import to_jsonable

__all__ = [
    "CoregistrationOutput",
    "StemCurveRows",
    "TreeRow",
    "TreesOutput",
    "read_coregistration_dir",
    "read_csv_rows",
    "read_trees_dir",
    "trees_output_from_inventory",
    "write_comparison",
    "write_edits",
    "write_poses_files",
    "write_targets_csv",
    "write_trees_tables",
]

PathLike = Union[str, os.PathLike[str]]

#: Columns of ``trees.csv``, in order (one row per tree; positions in the file's unit, sizes in metres).
TREE_COLUMNS = (
    "tree_id",
    "x",
    "y",
    "z",
    "dbh_m",
    "height_m",
    "height_source",
    "height_points_m",
    "crown_base_m",
    "crown_width_ew_m",
    "crown_width_ns_m",
    "crown_area_m2",
    "crown_volume_m3",
    "volume_m3",
    "stem_volume_m3",
    "branch_volume_m3",
    "qsm_dbh_m",
    "n_cylinders",
    "n_branches",
    "lean_deg",
    "dbh_arc_coverage",
    "dbh_rms_mm",
    "dbh_sigma_m",
    "dbh_ovality",
    "n_points",
    "wood_fraction",
    "stem_form_factor",
    "source",
    "dbh_quality",
    "height_quality",
    "crown_quality",
    "volume_quality",
    "flag",
)

#: Columns of a cylinder table (``cylinders/tree_NNNN.csv``), one row per cylinder.
CYLINDER_COLUMNS: tuple[str, ...] = (
    "cylinder_id",
    "parent_id",
    "extension_id",
    "branch_id",
    "branch_order",
    "position_in_branch",
    "start_x",
    "start_y",
    "start_z",
    "axis_x",
    "axis_y",
    "axis_z",
    "length_m",
    "radius_m",
    "surface_coverage",
    "mad_m",
    "added",
)
#: Cylinder columns written as whole numbers.
CYLINDER_INT_COLUMNS = {
    "cylinder_id",
    "parent_id",
    "extension_id",
    "branch_id",
    "branch_order",
    "position_in_branch",
    "added",
}

#: Columns of trees.csv read as text (everything else is a number; empty cells are NaN).
TEXT_COLUMNS = (
    "flag",
    "flags",
    "edited",
    "edit",
    "tree_id",
    "species",
    "source",
    "height_source",
    "dbh_quality",
    "height_quality",
    "crown_quality",
    "volume_quality",
)


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
    def height_source(self) -> str:
        """Where the height comes from: "points" (the tree's highest point) or "curve" (the
        plot's height-diameter curve); "points" when the table does not say."""
        return str(self.extra.get("height_source", "") or "points")

    def quality(self, measure: str) -> str:
        """The quality text of a measure ("dbh", "height", "crown", "volume"): "<how>; <trust>"
        ("" when the table has none)."""
        return str(self.extra.get(f"{measure}_quality", "") or "")

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
    #: the class the cylinder files are read as (``read_csv(path)``), e.g. the QSM's cylinder model
    cylinder_model: Any = None

    def tree(self, tree_id: int) -> TreeRow:
        for t in self.trees:
            if t.tree_id == tree_id:
                return t
        raise KeyError(tree_id)

    def cylinders(self, tree_id: int) -> Any:
        """The tree's cylinder model (an instance of ``cylinder_model``, read from its file; the
        columns when no model class was given), or None without one."""
        if int(tree_id) in self.models:
            return self.models[int(tree_id)]
        path = self.cylinder_files.get(int(tree_id))
        if path is None:
            return None
        return self.cylinder_model.read_csv(path) if self.cylinder_model is not None else read_cylinders_csv(path)

    @property
    def numeric_columns(self) -> tuple[str, ...]:
        return tuple(c for c in self.columns if c not in TEXT_COLUMNS)


def read_trees_dir(folder: PathLike, cylinder_model: Any = None) -> TreesOutput:
    """Read a trees result folder (see the module docstring); its cylinder files are read, when
    asked for, as ``cylinder_model`` (a class with ``read_csv``).

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
        trees.append(
            TreeRow(
                tree_id=int(tid),
                x=values.get("x", math.nan),
                y=values.get("y", math.nan),
                z=values.get("z", math.nan),
                values=values,
                flag=str(r.get("flag") or ""),
                extra=extra,
            )
        )
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
    return TreesOutput(
        folder=root,
        columns=tuple(header),
        trees=trees,
        curves=curves,
        cylinder_files=cylinder_files,
        cylinder_model=cylinder_model,
    )


def trees_output_from_inventory(
    inventory: Any, notes: Optional[Mapping[int, str]] = None, folder: PathLike = ""
) -> TreesOutput:
    """The same view of an in-memory :class:`~forestreg.engine.trees.inventory.TreeInventory`
    (file coordinates, as ``trees.csv`` would hold them); ``notes`` tree id -> edit note."""
    import dataclasses

    shift = np.asarray(inventory.origin_shift, dtype=np.float64)
    notes = dict(notes or {})
    trees, curves, models = [], {}, {}
    for rec in inventory.trees:
        row = rec.row(shift)
        values = {c: float(row[c]) for c in TREE_COLUMNS if c not in TEXT_COLUMNS and c in row}
        extra = {c: str(row[c]) for c in TEXT_COLUMNS if c in row and c not in ("flag", "tree_id")}
        if notes.get(rec.tree_id):
            extra["edited"] = notes[rec.tree_id]
        trees.append(
            TreeRow(
                tree_id=int(rec.tree_id),
                x=values["x"],
                y=values["y"],
                z=values["z"],
                values=values,
                flag=str(row.get("flag") or ""),
                extra=extra,
            )
        )
        c = rec.curve
        curves[int(rec.tree_id)] = StemCurveRows(
            height_m=np.asarray(c.heights_m, dtype=float),
            diameter_m=np.asarray(c.diameter_m, dtype=float),
            raw_diameter_m=np.asarray(c.raw_diameter_m, dtype=float),
            centres=np.asarray(c.centres, dtype=float) + shift,
            accepted=np.asarray(c.accepted, dtype=bool),
            interpolated=np.asarray(c.interpolated, dtype=bool),
            reasons=tuple(c.reasons),
        )
        if rec.cylinders is not None:
            models[int(rec.tree_id)] = dataclasses.replace(rec.cylinders, start=rec.cylinders.start + shift)
    columns = tuple(TREE_COLUMNS) + (("edited",) if notes else ())
    return TreesOutput(
        folder=Path(folder), columns=columns, trees=trees, curves=curves, cylinder_files={}, models=models
    )


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
    matched = np.array(
        [int(_number(r.get(key))) if key and math.isfinite(_number(r.get(key))) else -1 for r in rows], dtype=int
    )
    return xyz, matched


def read_coregistration_dir(folder: PathLike) -> CoregistrationOutput:
    """Read a co-registration result folder; :class:`ScanReadError` without a readable result.json."""
    root = Path(folder)
    path = root / "result.json"
    if not path.is_file():
        raise ScanReadError(
            f"{root} is not a co-registration result folder (no result.json; made by 'forestreg coregister --out DIR')"
        )
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
    return CoregistrationOutput(
        folder=root,
        result=result,
        matrix=matrix,
        ground_keypoints=g,
        ground_matched=gm,
        uav_keypoints=u,
        uav_matched=um,
    )


# ----------------------------------------------------------------------------- writers


def _fmt(v: Any) -> str:
    """A ``trees.csv`` cell: floats with 4 decimals, NaN empty."""
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.4f}"
    return str(v)


def csv_text(columns: Sequence[str], rows: Sequence[Mapping[str, Any]]) -> str:
    """CSV text of ``rows`` (dicts) under the header ``columns`` (missing cells empty)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_fmt(r.get(c, "")) for c in columns])
    return buf.getvalue()


STEM_CURVE_COLUMNS = (
    "tree_id",
    "s_m",
    "height_m",
    "diameter_m",
    "raw_diameter_m",
    "accepted",
    "interpolated",
    "x",
    "y",
    "z",
    "reason",
)


def write_trees_tables(out_dir: PathLike, inventory: Any, *, unit_scale: float = 1.0) -> Path:
    """Write ``trees.csv``, ``stem_curves.csv`` and ``cylinders/tree_NNNN.csv`` of a tree
    inventory (``rows()``, ``trees`` with ``curve`` and ``cylinders``, ``origin_shift``) into
    ``out_dir``; returns the trees.csv path. Positions (``x, y, z``, cylinder starts) are written
    in the input file's unit (``unit_scale`` metres per unit); every ``*_m`` figure stays in
    metres."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    shift = np.asarray(inventory.origin_shift, dtype=np.float64)
    rows = inventory.rows()
    file_rows = (
        rows
        if unit_scale == 1.0
        else [{**r, "x": r["x"] / unit_scale, "y": r["y"] / unit_scale, "z": r["z"] / unit_scale} for r in rows]
    )
    write_text_atomic(out / "trees.csv", csv_text(TREE_COLUMNS, file_rows))
    curve_rows = []
    for t in inventory.trees:
        c = t.curve
        for k in range(len(c.s_m)):
            centre = (c.centres[k] + shift) / unit_scale if np.isfinite(c.centres[k]).all() else [math.nan] * 3
            curve_rows.append(
                {
                    "tree_id": t.tree_id,
                    "s_m": c.s_m[k],
                    "height_m": c.heights_m[k],
                    "diameter_m": c.diameter_m[k],
                    "raw_diameter_m": c.raw_diameter_m[k],
                    "accepted": int(c.accepted[k]),
                    "interpolated": int(c.interpolated[k]),
                    "x": centre[0],
                    "y": centre[1],
                    "z": centre[2],
                    "reason": c.reasons[k],
                }
            )
    write_text_atomic(out / "stem_curves.csv", csv_text(STEM_CURVE_COLUMNS, curve_rows))
    cyl_dir = out / "cylinders"  # only when a tree has a cylinder model: no empty folder
    for t in inventory.trees:
        if t.cylinders is not None:
            cyl_dir.mkdir(exist_ok=True)
            table = dict(t.cylinders.to_table())
            start = (t.cylinders.start + shift) / unit_scale
            table.update(start_x=start[:, 0], start_y=start[:, 1], start_z=start[:, 2])
            write_cylinders_csv(cyl_dir / f"tree_{t.tree_id:04d}.csv", table)
    return out / "trees.csv"


def write_cylinders_csv(path: PathLike, table: Mapping[str, np.ndarray]) -> None:
    """Write a cylinder table (:data:`CYLINDER_COLUMNS`, one array per column) as CSV, atomically;
    floats with full precision (a read gives the same numbers back)."""
    cols = [np.asarray(table[c]) for c in CYLINDER_COLUMNS]
    lines = [",".join(CYLINDER_COLUMNS)]
    for i in range(len(cols[0]) if cols else 0):
        lines.append(
            ",".join(
                str(int(col[i])) if name in CYLINDER_INT_COLUMNS else repr(float(col[i]))
                for name, col in zip(CYLINDER_COLUMNS, cols)
            )
        )
    write_text_atomic(path, "\n".join(lines) + "\n")


def read_cylinders_csv(path: PathLike) -> dict[str, np.ndarray]:
    """The columns of a cylinder table written by :func:`write_cylinders_csv` (found by name, any
    order, extra columns ignored), rows in cylinder id order. A missing, unreadable or damaged file
    raises :class:`ScanReadError`."""
    try:
        with open(path, encoding="utf-8") as fh:
            lines = [line.strip() for line in fh if line.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise ScanReadError(f"cannot read cylinder table {path}: {exc}") from exc
    header = lines[0].split(",") if lines else []
    missing = [c for c in CYLINDER_COLUMNS if c not in header]
    if missing:
        raise ScanReadError(f"{path}: not a cylinder table, missing column(s) {', '.join(missing)}")
    cells = [line.split(",") for line in lines[1:]]
    short = [i + 2 for i, row in enumerate(cells) if len(row) != len(header)]
    if short:
        raise ScanReadError(f"{path}: damaged cylinder table, line {short[0]} does not have {len(header)} values")
    try:
        data = np.array([[float(v) for v in row] for row in cells], dtype=np.float64).reshape(len(cells), len(header))
    except ValueError as exc:
        raise ScanReadError(f"{path}: damaged cylinder table ({exc})") from exc
    col = {name: data[:, header.index(name)] for name in CYLINDER_COLUMNS}
    order = np.argsort(col["cylinder_id"], kind="stable")
    return {k: v[order] for k, v in col.items()}


class CylinderTableFile:
    """``write_csv`` / ``read_csv`` of a cylinder model (a class with ``to_table()`` and
    ``from_table(columns, source)``): the file format lives here."""

    def write_csv(self, path: PathLike) -> None:
        """Write the cylinder table as CSV (header line of :data:`CYLINDER_COLUMNS`), atomically."""
        write_cylinders_csv(path, self.to_table())  # type: ignore[attr-defined]

    @classmethod
    def read_csv(cls, path: PathLike) -> Any:
        """Read a table written by :meth:`write_csv`."""
        return cls.from_table(read_cylinders_csv(path), str(path))  # type: ignore[attr-defined]


class TreeTablesFile:
    """``write`` of a tree inventory: :func:`write_trees_tables`."""

    def write(self, out_dir: PathLike, *, unit_scale: float = 1.0) -> Path:
        """Write ``trees.csv``, ``stem_curves.csv`` and ``cylinders/`` into ``out_dir`` (see
        :func:`write_trees_tables`); returns the trees.csv path."""
        return write_trees_tables(out_dir, self, unit_scale=unit_scale)


def write_edits(
    trees_csv: PathLike,
    notes: Mapping[int, str],
    edits: Sequence[Mapping[str, Any]],
    cloud: Optional[Mapping[str, Any]] = None,
) -> None:
    """Add an ``edited`` column to ``trees_csv`` (the note of each tree's edits, "" for the others)
    and write the edits (their dicts) as ``edits.json`` beside it (replayable), with ``cloud``
    (``points`` and ``sha256`` of the cloud they were made on, or None)."""
    path = Path(trees_csv)
    text = path.read_text(encoding="utf-8")
    rows = list(csv.reader(io.StringIO(text)))
    if rows:
        header = rows[0]
        if "edited" not in header:
            header.append("edited")
            k = header.index("tree_id")
            for row in rows[1:]:
                try:
                    row.append(notes.get(int(float(row[k])), ""))
                except (ValueError, IndexError):
                    row.append("")
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerows(rows)
        write_text_atomic(path, buf.getvalue())
    write_text_atomic(
        path.parent / "edits.json",
        json.dumps(
            {
                "format": "forestreg-tree-edits",
                "version": 1,
                "cloud": None if cloud is None else dict(cloud),
                "edits": list(edits),
            },
            indent=2,
        )
        + "\n",
    )


def write_poses_files(out_dir: PathLike, body: Mapping[str, Any], transforms: Mapping[str, str]) -> Path:
    """Write ``poses.json`` (``body``) and one ``<scan>.transform.txt`` per entry of
    ``transforms`` (scan -> matrix text) into ``out_dir``; returns the path of ``poses.json``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, text in transforms.items():
        write_text_atomic(out / f"{name}.transform.txt", text)
    path = out / "poses.json"
    write_text_atomic(path, json.dumps(body, indent=2) + "\n")
    return path


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6f}"
    return str(value)


def write_comparison(comparison: Mapping[str, Any], out_dir: PathLike) -> tuple[Path, Path]:
    """Write ``comparison.json`` and ``comparison.csv`` (one row per pair) into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "comparison.json"
    write_text_atomic(json_path, json.dumps(comparison, indent=2) + "\n")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "moving",
            "reference",
            "auto_status",
            "auto_matched_vops",
            "auto_icp_std_m",
            "manual_status",
            "manual_targets",
            "manual_icp_std_m",
            "rotation_difference_deg",
            "translation_difference_m",
        ]
    )
    for p in comparison["pairs"]:
        w.writerow(
            [
                p["moving"],
                p["reference"],
                p["auto"]["status"],
                _cell(p["auto"]["matched"]),
                _cell(p["auto"]["icp_std_m"]),
                p["manual"]["status"],
                _cell(p["manual"]["targets"]),
                _cell(p["manual"]["icp_std_m"]),
                _cell(p["rotation_difference_deg"]),
                _cell(p["translation_difference_m"]),
            ]
        )
    w.writerow([])
    w.writerow(
        [
            "plot",
            "",
            "auto_target_residual_m",
            _cell(comparison["auto_target_residual_m"]),
            "",
            "manual_target_residual_m",
            _cell(comparison["manual_target_residual_m"]),
        ]
    )
    csv_path = out / "comparison.csv"
    write_text_atomic(csv_path, buf.getvalue())
    return json_path, csv_path


#: Columns of a targets CSV.
TARGET_COLUMNS = ("scan", "target", "x", "y", "z")


def write_targets_csv(path: PathLike, targets_by_scan: Mapping[str, Mapping[str, Any]]) -> None:
    """Write ``{scan: {target: xyz}}`` as a target CSV (``scan,target,x,y,z``), atomically.

    Coordinates are written with full float precision (a read gives the same numbers back).
    """
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(TARGET_COLUMNS)
    for scan, targets in targets_by_scan.items():
        for target, xyz in targets.items():
            v = np.asarray(xyz, dtype=np.float64).reshape(-1)
            if v.shape != (3,) or not np.isfinite(v).all():
                raise TargetError(
                    f"target {target!r} of scan {scan!r}: a centre must be three finite numbers, got {xyz!r}"
                )
            if not str(scan).strip() or not str(target).strip():
                raise TargetError("scan and target names must not be empty")
            writer.writerow([scan, target, *(repr(float(c)) for c in v)])
    write_text_atomic(path, buf.getvalue())


class ProjectFile:
    """Saving a plot project (a class with ``path`` and ``to_dict(relative_to=folder)``): the
    versioned JSON file, scan paths relative to it, written atomically, when the caller asks
    (:meth:`save`, :func:`save_to_its_file`); the engine's runs never save it themselves."""

    path: Optional[Path]

    def save(self, path: Optional[PathLike] = None) -> Path:
        """Write the project file atomically (scan paths relative to it) and remember the path."""
        target = Path(path) if path is not None else self.path
        if target is None:
            raise ProjectFileError("the project has no file yet: give a path to save it to")
        target = target.resolve()
        text = json.dumps(to_jsonable(self.to_dict(relative_to=target.parent)), indent=1)  # type: ignore[attr-defined]
        write_text_atomic(target, text + "\n")
        self.path = target
        return target


def save_to_its_file(project: Any) -> None:
    """Save a project (a :class:`ProjectFile`) to its file when it has one, else nothing: what the
    use cases hand a run as its ``on_link_done``, so an interrupted run loses nothing already
    computed (the engine's runs report each finished link and write no file)."""
    if project.path is not None:
        project.save()


# ----------------------------------------------------------------------------- evaluation


def table_text(rows: Sequence[Mapping[str, Any]], empty_header: Optional[Sequence[str]] = None) -> str:
    buf = io.StringIO()
    header = list(rows[0].keys()) if rows else list(empty_header or [])
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    for r in rows:
        writer.writerow([table_cell(r.get(h)) for h in header])
    return buf.getvalue()


def table_cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (float, np.floating)):
        return "" if not math.isfinite(float(value)) else f"{float(value):.6g}"
    if isinstance(value, (np.integer,)):
        return str(int(value))
    return str(value)


def file_stem(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name.strip()) or "run"


def write_evaluation_files(
    out_dir: PathLike,
    tables: Mapping[str, tuple[Sequence[Mapping[str, Any]], Optional[Sequence[str]]]],
    doc: Mapping[str, Any],
    figures: Mapping[str, bytes],
) -> dict[str, Path]:
    """Write an evaluation's files into ``out_dir`` (created if missing), each atomically: the CSV
    ``tables`` (file stem -> (rows, header when there are no rows)), ``evaluation.json`` (``doc``)
    and ``figures/<name>.png`` (PNG bytes). Returns the paths by name: the table stems, "json"
    and each figure's name."""
    from ..core.atomic import atomic_path

    out = Path(out_dir)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    for stem, (rows, empty_header) in tables.items():
        paths[stem] = out / f"{stem}.csv"
        write_text_atomic(paths[stem], table_text(rows, empty_header=empty_header))
    paths["json"] = out / "evaluation.json"
    write_text_atomic(paths["json"], json.dumps(doc, indent=2, ensure_ascii=False) + "\n")
    for name, png in figures.items():
        paths[name] = out / "figures" / f"{name}.png"
        with atomic_path(paths[name]) as tmp:
            tmp.write_bytes(png)
    return paths
