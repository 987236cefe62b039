"""Comparison of estimated tree parameters with field records (paper section 5.2.2, table 3).

Tables of trees (one row per tree: ``tree_id``, position ``x``, ``y`` in the plot frame, metres,
and any of the parameters in :data:`PARAMETERS`) come from CSV files (:func:`read_tree_table`) or
from rows in memory (:func:`tree_table_from_rows`, e.g. the tree pipeline's output). Estimated
trees are paired one-to-one with field trees (:func:`match_trees`: by position, Hungarian
assignment on the horizontal distance within a gate, or by tree id); :func:`evaluate` then gives,
per parameter, the paper's figures:

* ``n``: pairs where both values are known;
* ``R2 = 1 - SS_res / SS_tot``, the coefficient of determination of the estimates as predictions
  of the field values (``SS_res = sum (est - field)^2``, ``SS_tot = sum (field - mean field)^2``;
  not the squared correlation of a fitted line: a biased estimate lowers it, and it can be
  negative when the estimates are worse than the field mean); undefined (NaN, with the reason in
  ``r2_note``) with fewer than 2 pairs or field values that are all equal;
* ``RMSE = sqrt(mean (est - field)^2)`` in the parameter's unit; ``rRMSE = 100 RMSE / mean field``
  (%); ``bias = mean (est - field)``;

and the detection figures: matched trees, omitted field trees (no estimate), commission
(estimated trees with no field tree). :func:`forestreg.app.evaluation.write_evaluation` writes CSV, JSON, scatter plots
and an HTML report for one or several runs side by side (e.g. "ground" against "fused").
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Optional, Sequence, Union

import numpy as np

from ..core.errors import ForestregError, ParameterError
from ..core.outcome import Outcome


class TreeTableError(ForestregError):
    """A table of trees cannot be read or holds implausible values (wrong units, duplicates)."""


@dataclass(frozen=True)
class ParameterInfo:
    """A tree parameter: its column, the paper's symbol, its unit, and the largest plausible value
    (larger values mean wrong units)."""

    column: str
    label: str
    unit: str
    description: str
    max_plausible: float


#: The parameters compared, in the order of the paper's table 3 (then crown base height).
PARAMETERS: dict[str, ParameterInfo] = {
    p.column: p
    for p in (
        ParameterInfo("dbh_m", "DBH", "m", "diameter at breast height (1.3 m)", 3.0),
        ParameterInfo("height_m", "H", "m", "tree height", 130.0),
        ParameterInfo("volume_m3", "V", "m³", "wood volume (stem and branches)", 500.0),
        ParameterInfo("crown_area_m2", "CA", "m²", "crown projection area", 3000.0),
        ParameterInfo("crown_volume_m3", "CV", "m³", "crown volume", 50000.0),
        ParameterInfo("crown_base_m", "CBH", "m", "crown base height", 130.0),
    )
}
#: Column name aliases accepted in files (lower case, spaces and dashes as underscores).
_ALIASES = {
    "id": "tree_id",
    "tree": "tree_id",
    "treeid": "tree_id",
    "tree_no": "tree_id",
    "tree_number": "tree_id",
    "x_m": "x",
    "y_m": "y",
    "h_m": "height_m",
    "height": None,
    "dbh": None,
    "cbh_m": "crown_base_m",
    "crown_base_height_m": "crown_base_m",
    "ca_m2": "crown_area_m2",
    "cv_m3": "crown_volume_m3",
    "v_m3": "volume_m3",
}
_MISSING = {"", "na", "n/a", "nan", "null", "none", "-", "--", "?"}


@dataclass(frozen=True, eq=False)
class TreeTable:
    """Trees: ids (str), positions (m, NaN where unknown) and parameter values (NaN = missing).

    ``values`` maps a column of :data:`PARAMETERS` to a float array; ``notes`` records what was
    done on reading (unit conversions); ``source`` names where the table came from.
    """

    tree_id: np.ndarray
    x: np.ndarray
    y: np.ndarray
    values: dict[str, np.ndarray]
    source: str = ""
    notes: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.tree_id)

    @property
    def xy(self) -> np.ndarray:
        return np.c_[self.x, self.y]

    @property
    def parameters(self) -> list[str]:
        """The parameters this table holds, in :data:`PARAMETERS` order."""
        return [p for p in PARAMETERS if p in self.values]


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------


def read_tree_table(path: Union[str, os.PathLike[str]]) -> TreeTable:
    """Read a CSV table of trees (comma, semicolon or tab separated, header row first).

    Columns: ``tree_id``, ``x``, ``y`` (metres, the plot frame) and any of ``dbh_m``,
    ``height_m``, ``crown_base_m``, ``crown_area_m2``, ``crown_volume_m3``, ``volume_m3``; other
    columns are ignored. Field sheets often give the diameter in centimetres: a ``dbh_cm`` column
    is converted to metres (and the conversion recorded in ``notes``). Values that cannot be in
    the stated unit are an error, never silently used: a ``dbh_m`` above 3 m (centimetres?), a
    ``dbh_cm`` column whose values are all below 2 (metres?), heights above 130 m.
    Empty cells, ``NA`` and ``-`` are missing values.

    Raises
    ------
    TreeTableError
        The file is missing or unreadable, lacks a required column, has duplicate tree ids,
        non-numbers, negative or implausible values.
    """
    from ..io.base import read_text_lines

    p, numbered = read_text_lines(path, TreeTableError, "tree table")
    lines = [ln for _, ln in numbered]
    if not lines:
        raise TreeTableError(f"tree table {p} is empty")
    delimiter = max((",", ";", "\t"), key=lambda d: lines[0].count(d))
    reader = csv.reader(io.StringIO("\n".join(lines)), delimiter=delimiter)
    rows = list(reader)
    header = [_normalise_name(h) for h in rows[0]]
    records = []
    for number, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise TreeTableError(f"{p}: line {number} has {len(row)} fields, the header {len(header)}")
        records.append(dict(zip(header, row)))
    return _table(header, records, str(p))


def tree_table_from_rows(rows: Sequence[Mapping[str, Any]], source: str = "rows") -> TreeTable:
    """A :class:`TreeTable` from rows of dicts (same columns and checks as :func:`read_tree_table`)."""
    header: list[str] = []
    records = []
    for row in rows:
        rec = {_normalise_name(k): v for k, v in row.items()}
        for k in rec:
            if k not in header:
                header.append(k)
        records.append(rec)
    return _table(header, records, source)


def as_tree_table(table: Union[TreeTable, str, os.PathLike[str], Sequence[Mapping[str, Any]]]) -> TreeTable:
    """A :class:`TreeTable` from a table, a CSV path or rows of dicts."""
    if isinstance(table, TreeTable):
        return table
    if isinstance(table, (str, os.PathLike)):
        return read_tree_table(table)
    return tree_table_from_rows(table)


def _normalise_name(name: Any) -> str:
    key = re.sub(r"[\s\-]+", "_", str(name).strip().lower())
    return key


def _table(header: Sequence[str], records: Sequence[Mapping[str, Any]], source: str) -> TreeTable:
    columns = set(header)
    renamed: dict[str, str] = {}
    for name in header:
        if name in _ALIASES:
            target = _ALIASES[name]
            if target is None:
                raise TreeTableError(
                    f"{source}: column {name!r} has no unit; name it with its unit, e.g. "
                    + ("dbh_m or dbh_cm" if name in ("dbh", "d") else "height_m")
                )
            if target not in columns:
                renamed[name] = target
    header = [renamed.get(h, h) for h in header]
    records = [{renamed.get(k, k): v for k, v in r.items()} for r in records]
    missing = [c for c in ("tree_id", "x", "y") if c not in header]
    if missing:
        raise TreeTableError(
            f"{source}: missing column(s) {', '.join(missing)}; a tree table needs tree_id, x, y (metres)"
        )
    if not records:
        raise TreeTableError(f"{source}: holds no trees")
    ids = np.array([_id_text(r.get("tree_id")) for r in records], dtype=object)
    if any(i == "" for i in ids):
        raise TreeTableError(f"{source}: {sum(i == '' for i in ids)} row(s) have no tree_id")
    uniq, counts = np.unique(ids.astype(str), return_counts=True)
    if (counts > 1).any():
        raise TreeTableError(f"{source}: duplicate tree_id(s) {', '.join(uniq[counts > 1][:5])}")
    x = _numbers(records, "x", source)
    y = _numbers(records, "y", source)
    notes: list[str] = []
    values: dict[str, np.ndarray] = {}
    if "dbh_cm" in header and "dbh_m" not in header:
        cm = _numbers(records, "dbh_cm", source)
        finite = cm[np.isfinite(cm)]
        if len(finite) and finite.min() < 0:
            raise TreeTableError(f"{source}: column dbh_cm has negative values (tree {ids[np.nanargmin(cm)]})")
        if len(finite) and finite.max() < 2.0:
            raise TreeTableError(
                f"{source}: column dbh_cm holds values up to {finite.max():.3g}, which look like metres, not centimetres; "
                "rename the column dbh_m"
            )
        values["dbh_m"] = cm / 100.0
        notes.append("dbh_cm converted to metres (divided by 100)")
    for name, info in PARAMETERS.items():
        if name not in header:
            continue
        v = _numbers(records, name, source)
        finite = v[np.isfinite(v)]
        if len(finite) and finite.min() < 0:
            raise TreeTableError(f"{source}: column {name} has negative values (tree {ids[np.nanargmin(v)]})")
        if len(finite) and finite.max() > info.max_plausible:
            worst = ids[np.nanargmax(v)]
            hint = _unit_hint(name, finite)
            raise TreeTableError(
                f"{source}: column {name} has a value of {finite.max():.4g} {info.unit} (tree {worst}), more than "
                f"{info.max_plausible:g} {info.unit}{hint}"
            )
        values[name] = v
    dbh = values.get("dbh_m")
    if dbh is not None and (dbh == 0).any():
        bad = np.flatnonzero(dbh == 0)[0]
        raise TreeTableError(
            f"{source}: tree {ids[bad]} has a DBH of 0 m: no tree is 0 m thick; leave a DBH not measured empty"
        )
    return TreeTable(ids, x, y, values, source, tuple(notes))


def _id_text(value: Any) -> str:
    """A tree id as text; whole numbers written as floats (3.0) become "3"."""
    if value is None:
        return ""
    if isinstance(value, (float, np.floating)) and math.isfinite(value) and float(value).is_integer():
        return str(int(value))
    return str(value).strip()


def _numbers(records: Sequence[Mapping[str, Any]], column: str, source: str) -> np.ndarray:
    out = np.full(len(records), np.nan)
    for i, r in enumerate(records):
        v = r.get(column)
        if v is None or (isinstance(v, str) and v.strip().lower() in _MISSING):
            continue
        try:
            f = float(v.strip().replace(",", ".") if isinstance(v, str) else v)
        except (TypeError, ValueError):
            raise TreeTableError(
                f"{source}: tree {r.get('tree_id', i + 1)}: {column} = {v!r} is not a number"
            ) from None
        if math.isinf(f):
            raise TreeTableError(
                f"{source}: tree {r.get('tree_id', i + 1)}: {column} = {v!r} is infinite: leave a value not measured empty"
            )
        if math.isfinite(f):
            out[i] = f
    return out


# ------------------------------------------------------------------------------------------------
# matching
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class TreeMatch:
    """One-to-one pairs of estimated and field trees.

    ``estimated_index[k]`` and ``field_index[k]`` index the two tables; ``distance_m[k]`` is
    their horizontal distance (NaN where a position is unknown). ``omitted``: field trees left
    without an estimate; ``commission``: estimated trees with no field tree.
    """

    estimated_index: np.ndarray
    field_index: np.ndarray
    distance_m: np.ndarray
    omitted: np.ndarray
    commission: np.ndarray
    by: str
    max_distance_m: float

    def __len__(self) -> int:
        return len(self.estimated_index)


def match_trees(
    estimated: Union[TreeTable, Sequence[Mapping[str, Any]]],
    field_trees: Union[TreeTable, Sequence[Mapping[str, Any]]],
    max_distance_m: float = 1.0,
    by: str = "position",
) -> TreeMatch:
    """Pair estimated trees with field trees one-to-one.

    ``by="position"``: the assignment with the most pairs within ``max_distance_m`` (horizontal
    stem distance, metres), and among those the least total distance (Hungarian algorithm, run on
    each group of trees linked by distances within the gate, so large plots stay quick).
    ``by="id"``: trees with the same ``tree_id`` (no gate; the distance is reported).
    """
    est, fld = as_tree_table(estimated), as_tree_table(field_trees)
    if by not in ("position", "id"):
        raise ParameterError(f"match by {by!r} is unknown; use 'position' or 'id'")
    if not (isinstance(max_distance_m, (int, float)) and math.isfinite(max_distance_m) and max_distance_m > 0):
        raise ParameterError(f"max_distance_m must be a positive distance in metres, not {max_distance_m!r}")
    if by == "id":
        where = {str(t): j for j, t in enumerate(fld.tree_id)}
        pairs = [(i, where[str(t)]) for i, t in enumerate(est.tree_id) if str(t) in where]
        ei = np.array([p[0] for p in pairs], dtype=np.int64)
        fi = np.array([p[1] for p in pairs], dtype=np.int64)
    else:
        for table, what in ((est, "estimated"), (fld, "field")):
            bad = ~(np.isfinite(table.x) & np.isfinite(table.y))
            if bad.any():
                raise TreeTableError(
                    f"{what} trees {', '.join(map(str, table.tree_id[bad][:5]))} have no position; "
                    "give x and y, or match by id"
                )
        ei, fi = _assign_by_position(est.xy, fld.xy, float(max_distance_m))
    order = np.argsort(fi, kind="stable")
    ei, fi = ei[order], fi[order]
    dist = np.hypot(est.x[ei] - fld.x[fi], est.y[ei] - fld.y[fi]) if len(ei) else np.zeros(0)
    omitted = np.setdiff1d(np.arange(len(fld)), fi)
    commission = np.setdiff1d(np.arange(len(est)), ei)
    return TreeMatch(ei, fi, dist, omitted, commission, by, float(max_distance_m))


def _assign_by_position(est_xy: np.ndarray, fld_xy: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
    from scipy.optimize import linear_sum_assignment
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    ne, nf = len(est_xy), len(fld_xy)
    if ne == 0 or nf == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    near = cKDTree(est_xy).sparse_distance_matrix(cKDTree(fld_xy), gate, output_type="ndarray")
    if len(near) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ii, jj, dd = near["i"].astype(np.int64), near["j"].astype(np.int64), near["v"]
    graph = coo_matrix((np.ones(len(ii)), (ii, ne + jj)), shape=(ne + nf, ne + nf))
    _, label = connected_components(graph, directed=False)
    out_e, out_f = [], []
    comp = label[ii]
    for c in np.unique(comp):
        sel = comp == c
        e_ids, e_local = np.unique(ii[sel], return_inverse=True)
        f_ids, f_local = np.unique(jj[sel], return_inverse=True)
        # a pair outside the gate costs more than any set of gated pairs: the most pairs first
        big = gate * (len(e_ids) + len(f_ids) + 1)
        cost = np.full((len(e_ids), len(f_ids)), big)
        cost[e_local, f_local] = dd[sel]
        r, c2 = linear_sum_assignment(cost)
        ok = cost[r, c2] < big
        out_e.append(e_ids[r[ok]])
        out_f.append(f_ids[c2[ok]])
    return np.concatenate(out_e), np.concatenate(out_f)


# ------------------------------------------------------------------------------------------------
# statistics
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ParameterStats:
    """Agreement of one parameter over the matched trees (definitions: module docstring).

    ``estimate`` and ``field_value`` are the ``n`` compared values (parameter unit), with the
    trees' ids in ``estimated_ids`` and ``field_ids``.
    """

    parameter: str
    n: int
    r2: float
    rmse: float
    rrmse_percent: float
    bias: float
    field_mean: float
    estimate: np.ndarray
    field_value: np.ndarray
    estimated_ids: np.ndarray
    field_ids: np.ndarray
    #: why R2 is undefined (NaN), e.g. "field values all equal"; empty when it is defined
    r2_note: str = ""

    @property
    def info(self) -> ParameterInfo:
        return PARAMETERS[self.parameter]

    def r2_text(self, digits: int = 2) -> str:
        """R2 for a line of text: ``0.93``, or ``n/a (<why>)`` where it is undefined."""
        if math.isfinite(self.r2):
            return f"{self.r2:.{digits}f}"
        return f"n/a ({self.r2_note})" if self.r2_note else "n/a"

    def to_dict(self) -> dict[str, Any]:
        info = self.info
        out = {
            "parameter": self.parameter,
            "label": info.label,
            "unit": info.unit,
            "n": self.n,
            "r2": _json_num(self.r2),
            "rmse": _json_num(self.rmse),
            "rrmse_percent": _json_num(self.rrmse_percent),
            "bias": _json_num(self.bias),
            "field_mean": _json_num(self.field_mean),
        }
        if not math.isfinite(self.r2):
            out["r2_note"] = self.r2_note or "undefined"
        return out


def agreement(estimate: Iterable[float], field_value: Iterable[float]) -> dict[str, float]:
    """``n``, ``r2``, ``rmse``, ``rrmse_percent``, ``bias`` and ``field_mean`` of estimates
    against field values (pairs with a missing value are skipped; NaN where undefined: no pairs,
    R2 with fewer than 2 pairs or no spread in the field values (:func:`r2_undefined`), rRMSE
    with a zero field mean)."""
    e = np.asarray(list(estimate) if not isinstance(estimate, np.ndarray) else estimate, dtype=np.float64)
    f = np.asarray(list(field_value) if not isinstance(field_value, np.ndarray) else field_value, dtype=np.float64)
    ok = np.isfinite(e) & np.isfinite(f)
    e, f = e[ok], f[ok]
    n = len(e)
    nan = float("nan")
    if n == 0:
        return {"n": 0, "r2": nan, "rmse": nan, "rrmse_percent": nan, "bias": nan, "field_mean": nan}
    diff = e - f
    rmse = float(np.sqrt(np.mean(diff**2)))
    mean_f = float(f.mean())
    ss_tot = float(np.sum((f - mean_f) ** 2))
    r2 = nan if r2_undefined(f) or ss_tot <= 0 else 1.0 - float(np.sum(diff**2)) / ss_tot
    rrmse = 100.0 * rmse / mean_f if mean_f != 0 else nan
    return {"n": n, "r2": r2, "rmse": rmse, "rrmse_percent": rrmse, "bias": float(diff.mean()), "field_mean": mean_f}


def r2_undefined(field_value: Iterable[float]) -> str:
    """Why R2 cannot be computed over these field values (the finite ones), or "" when it can:
    fewer than 2 values, or values that are all equal (no spread to explain: SS_tot is 0, or only
    the rounding of their mean, which would give an R2 of -1e30)."""
    f = np.asarray(list(field_value) if not isinstance(field_value, np.ndarray) else field_value, dtype=np.float64)
    f = f[np.isfinite(f)]
    if len(f) < 2:
        return f"fewer than 2 pairs ({len(f)})"
    if float(np.ptp(f)) <= 1e-9 * max(float(np.abs(f).max()), 1e-300):
        return f"field values all equal ({f[0]:.6g})"
    return ""


@dataclass(frozen=True)
class Detection:
    """Tree detection: matched pairs, omitted field trees, commission (extra estimated trees)."""

    field_trees: int
    estimated_trees: int
    matched: int
    omitted: int
    commission: int

    @property
    def omission_rate(self) -> float:
        """Omitted field trees / field trees."""
        return self.omitted / self.field_trees if self.field_trees else float("nan")

    @property
    def commission_rate(self) -> float:
        """Estimated trees with no field tree / estimated trees."""
        return self.commission / self.estimated_trees if self.estimated_trees else float("nan")

    def to_dict(self) -> dict[str, Any]:
        return {
            "field_trees": self.field_trees,
            "estimated_trees": self.estimated_trees,
            "matched": self.matched,
            "omitted": self.omitted,
            "commission": self.commission,
            "omission_rate": _json_num(self.omission_rate),
            "commission_rate": _json_num(self.commission_rate),
        }


@dataclass(frozen=True, eq=False)
class Evaluation(Outcome):
    """The comparison of one set of estimates (a "run", e.g. ground-based or fused) with the field.
    Failed (falsy) when no estimated tree matched a field tree (the reason says why)."""

    match: TreeMatch
    detection: Detection
    stats: dict[str, ParameterStats]
    estimated: TreeTable
    field_table: TreeTable
    status: str = "ok"
    reason: str = ""
    timings: dict[str, float] = field(default_factory=dict)

    method = "field records matched by position or id"
    matrix = None

    def evidence(self) -> dict[str, Any]:
        return {"detection": self.detection.to_dict()}

    def summary(self) -> str:
        """One line: the field trees matched and, per parameter with a pair, R2 (or "n/a" and
        why) and rRMSE; the reason when no tree matched."""
        if not self.ok:
            return self.reason
        d = self.detection
        figures = ", ".join(
            f"{p} R2 {st.r2_text()} rRMSE {_text(st.rrmse_percent, '.1f')} %"
            for p, st in self.stats.items()
            if st.n >= 1
        )
        return f"{d.matched} of {d.field_trees} field trees matched" + (f"; {figures}" if figures else "")

    def to_dict(self, *, pairs: bool = True) -> dict[str, Any]:
        """JSON-able figures (and, with ``pairs``, every matched pair with its values)."""
        out: dict[str, Any] = {
            "match": {"by": self.match.by, "max_distance_m": self.match.max_distance_m},
            "detection": self.detection.to_dict(),
            "parameters": {k: s.to_dict() for k, s in self.stats.items()},
            "notes": {"estimated": list(self.estimated.notes), "field": list(self.field_table.notes)},
        }
        if pairs:
            out["pairs"] = pair_rows(self)
            out["omitted_field_trees"] = [str(t) for t in self.field_table.tree_id[self.match.omitted]]
            out["commission_trees"] = [str(t) for t in self.estimated.tree_id[self.match.commission]]
        return out


def evaluate(
    estimated: Union[TreeTable, str, os.PathLike[str], Sequence[Mapping[str, Any]]],
    field_trees: Union[TreeTable, str, os.PathLike[str], Sequence[Mapping[str, Any]]],
    *,
    by: str = "position",
    max_distance_m: float = 1.0,
    parameters: Optional[Sequence[str]] = None,
) -> Evaluation:
    """Match estimated trees to field trees and compute the paper's figures per parameter.

    ``parameters``: which to compare (default: every parameter both tables hold); a requested
    parameter missing from a table gets ``n = 0``.
    """
    est, fld = as_tree_table(estimated), as_tree_table(field_trees)
    if by == "position":
        _check_position_units(est, fld)
    match = match_trees(est, fld, max_distance_m=max_distance_m, by=by)
    if parameters is None:
        names = [p for p in PARAMETERS if p in est.values and p in fld.values]
    else:
        unknown = [p for p in parameters if p not in PARAMETERS]
        if unknown:
            raise ParameterError(f"unknown parameter(s) {', '.join(unknown)}; known: {', '.join(PARAMETERS)}")
        names = list(parameters)
    stats: dict[str, ParameterStats] = {}
    for name in names:
        e_all = est.values.get(name, np.full(len(est), np.nan))[match.estimated_index]
        f_all = fld.values.get(name, np.full(len(fld), np.nan))[match.field_index]
        ok = np.isfinite(e_all) & np.isfinite(f_all)
        fig = agreement(e_all, f_all)
        stats[name] = ParameterStats(
            name,
            int(fig["n"]),
            fig["r2"],
            fig["rmse"],
            fig["rrmse_percent"],
            fig["bias"],
            fig["field_mean"],
            e_all[ok],
            f_all[ok],
            est.tree_id[match.estimated_index][ok],
            fld.tree_id[match.field_index][ok],
            r2_undefined(f_all[ok]),
        )
        _check_value_units(name, e_all[ok], f_all[ok], fld.source)
    detection = Detection(len(fld), len(est), len(match), len(match.omitted), len(match.commission))
    if detection.matched == 0:
        how = (
            "no shared tree ids"
            if by == "id"
            else f"no tree within {max_distance_m:g} m of a field tree (same coordinates and units?)"
        )
        return Evaluation(
            match,
            detection,
            stats,
            est,
            fld,
            status="failed",
            reason=f"0 of {detection.field_trees} field trees matched ({how})",
        )
    return Evaluation(match, detection, stats, est, fld)


#: Unit factors a field sheet may be off by (name, field value / value in the right unit).
_UNIT_FACTORS = (("millimetres", 1000.0), ("centimetres", 100.0), ("decimetres", 10.0), ("feet", 1.0 / 0.3048))


def _unit_hint(name: str, values: np.ndarray) -> str:
    """A hint at the unit an implausibly large column is in (from its median)."""
    med = float(np.median(values))
    if name == "dbh_m":
        if med > 150.0:
            return "; they look like millimetres: divide by 1000 (or by 10 and name the column dbh_cm)"
        return "; they look like centimetres: name the column dbh_cm"
    for unit, factor in sorted(_UNIT_FACTORS, key=lambda u: u[1]):
        if med / factor < PARAMETERS[name].max_plausible / 3:
            return f"; they look like {unit}, not {PARAMETERS[name].unit}: convert them"
    return "; check the unit"


def _check_value_units(name: str, estimate: np.ndarray, field_value: np.ndarray, source: str) -> None:
    """Refuse field values that are a unit factor off the matched estimates (heights in feet,
    diameters in cm named _m): R2 of such a comparison would be meaningless."""
    if len(estimate) < 5:
        return
    e, f = float(np.median(estimate)), float(np.median(field_value))
    if e <= 0 or f <= 0:
        return
    ratio = f / e
    for unit, factor in _UNIT_FACTORS:
        if abs(np.log(ratio / factor)) < np.log(1.3):
            raise TreeTableError(
                f"{source}: the field {name} values are {ratio:.3g} times the estimates (median {f:.4g} vs "
                f"{e:.4g} {PARAMETERS[name].unit}): they look like {unit}; convert them to {PARAMETERS[name].unit}"
            )


def _check_position_units(est: "TreeTable", fld: "TreeTable") -> None:
    """Refuse field positions whose spread is a unit factor off the estimated trees' (mm or cm
    against metres): position matching would find nothing."""
    if len(est) < 3 or len(fld) < 3:
        return

    def spread(t: "TreeTable") -> float:
        xy = np.column_stack([t.x, t.y])
        xy = xy[np.isfinite(xy).all(axis=1)]
        return float(np.ptp(xy, axis=0).max()) if len(xy) >= 3 else 0.0

    se, sf = spread(est), spread(fld)
    if se <= 0 or sf <= 0:
        return
    ratio = sf / se
    for unit, factor in _UNIT_FACTORS[:2]:
        if ratio > factor / 3:
            raise TreeTableError(
                f"{fld.source}: the field positions spread {sf:,.0f} units against {se:,.1f} m for the trees: "
                f"they look like {unit}; convert them to metres (same coordinates as the cloud)"
            )


def pair_rows(evaluation: Evaluation) -> list[dict[str, Any]]:
    """One dict per matched pair: ids, distance and each parameter's estimate and field value."""
    m, est, fld = evaluation.match, evaluation.estimated, evaluation.field_table
    rows = []
    for e, f, d in zip(m.estimated_index, m.field_index, m.distance_m):
        row: dict[str, Any] = {
            "field_id": str(fld.tree_id[f]),
            "estimated_id": str(est.tree_id[e]),
            "distance_m": _json_num(d),
        }
        for name in evaluation.stats:
            row[f"{name}_estimated"] = _json_num(est.values[name][e]) if name in est.values else None
            row[f"{name}_field"] = _json_num(fld.values[name][f]) if name in fld.values else None
        rows.append(row)
    return rows


def _text(value: float, spec: str) -> str:
    """A figure for a line of text; "n/a" where it is undefined."""
    return format(value, spec) if math.isfinite(value) else "n/a"


def _json_num(value: Any) -> Optional[float]:
    if value is None:
        return None
    v = float(value)
    return v if math.isfinite(v) else None


__all__ = [
    "PARAMETERS",
    "ParameterInfo",
    "TreeTable",
    "TreeTableError",
    "TreeMatch",
    "ParameterStats",
    "Detection",
    "Evaluation",
    "read_tree_table",
    "tree_table_from_rows",
    "as_tree_table",
    "match_trees",
    "agreement",
    "r2_undefined",
    "evaluate",
    "pair_rows",
]
