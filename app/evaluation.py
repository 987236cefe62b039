"""Evaluation: measured trees against field records (R², RMSE, rRMSE per parameter, detection
rates; the paper's table 3).

:func:`evaluate_tables` reads the tree tables and the field records, matches and scores them
(:func:`forestreg.engine.trees.evaluate.evaluate`) and writes the output folder
(``evaluation.csv``/``.json``, ``detection.csv``, figures, ``report.html``) as one transaction.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Optional, Sequence, Union

from .common import RunOutcome, refuse_same_file

if TYPE_CHECKING:
    from ..engine.trees.evaluate import Evaluation


@dataclass(frozen=True, eq=False)
class EvaluationOutcome(RunOutcome):
    """The evaluation of named runs: ``runs`` (name -> the engine's
    :class:`~forestreg.engine.trees.evaluate.Evaluation`), ``lines`` (one per run: matched trees
    and figures, then the files), ``paths`` (the files written by name). Failed when a run
    matched no field tree."""

    method = "field records matched by position or id"
    runs: dict = field(default_factory=dict)
    lines: tuple = ()
    paths: dict = field(default_factory=dict)

    def evidence(self) -> dict:
        return {name: ev.detection.to_dict() for name, ev in self.runs.items()}


def evaluate_tables(
    named: Sequence[tuple[str, str | Path]],
    field_path,
    out: str | Path,
    *,
    by: str = "position",
    max_distance: float = 1.0,
    progress=None,
    cancel=None,
) -> EvaluationOutcome:
    """Evaluate the named tree tables (``[(name, trees.csv), ...]``) against ``field_path`` into
    the folder ``out`` (a transaction)."""
    from ..engine.core.atomic import check_output_folder, output_folder
    from ..engine.trees.evaluate import read_tree_table

    for _, path in named:
        refuse_same_file(path, field_path, "the tree table and the field records are the same file")
    out = check_output_folder(out, "evaluate", inputs=[field_path, *[p for _, p in named]])
    field_table = read_tree_table(field_path)
    tables = [(name, read_tree_table(path)) for name, path in named]  # every table checked before the work
    if cancel is not None:
        cancel.raise_if_cancelled()
    with output_folder(out, "evaluate") as tmp:
        outcome = evaluate_into(tmp, tables, field_table, by=by, max_distance=max_distance, shown_as=out)
    return outcome


def evaluate_runs(named, field_table, *, by: str = "position", max_distance: float = 1.0) -> dict:
    """Name -> :class:`~forestreg.engine.trees.evaluate.Evaluation` of each named tree table (no
    file written)."""
    from ..engine.trees.evaluate import evaluate as evaluate_table

    return {name: evaluate_table(table, field_table, by=by, max_distance_m=max_distance) for name, table in named}


def evaluate(
    estimated, field_trees, *, by: str = "position", max_distance_m: float = 1.0, parameters=None
) -> "Evaluation":
    """Match estimated trees to field trees and compute the paper's figures per parameter
    (:func:`forestreg.engine.trees.evaluate.evaluate`, same arguments), the inputs checked first as
    the ``evaluate`` command checks them.

    Each table is a :class:`~forestreg.engine.trees.evaluate.TreeTable`, a CSV file's path, rows
    (a list of dicts: ``tree_id``, ``x``, ``y`` in metres and any parameters) or a
    :class:`~forestreg.engine.trees.inventory.TreeInventory` (its rows); ``by`` "position" or "id";
    ``max_distance_m`` a positive number; ``parameters`` None or names of parameters. Anything else
    raises the product's error naming what is expected
    (:class:`~forestreg.engine.core.errors.InvalidArgumentError`,
    :class:`~forestreg.engine.core.errors.ParameterError`; a table that cannot be read or holds
    implausible values: :class:`~forestreg.engine.trees.evaluate.TreeTableError`)."""
    import math

    from ..engine.core.errors import ParameterError
    from ..engine.trees.evaluate import evaluate as evaluate_table

    tables = [_tree_table_input(t, what) for t, what in ((estimated, "estimated"), (field_trees, "field_trees"))]
    if by not in ("position", "id"):
        raise ParameterError(f"by: 'position' or 'id', got {by!r}")
    try:
        distance = float(max_distance_m)
    except (TypeError, ValueError):
        distance = math.nan
    if isinstance(max_distance_m, bool) or not math.isfinite(distance) or distance <= 0:
        raise ParameterError(f"max_distance_m: a positive number of metres, got {max_distance_m!r}")
    if parameters is not None:
        if isinstance(parameters, (str, bytes)) or not all(isinstance(p, str) for p in parameters):
            raise ParameterError(
                f"parameters: a list of parameter names (e.g. ['dbh_m', 'height_m']), got {parameters!r}"
            )
        parameters = list(parameters)
    return evaluate_table(tables[0], tables[1], by=by, max_distance_m=distance, parameters=parameters)


def _tree_table_input(table, what: str):
    """A table :func:`evaluate` can take (a TreeInventory as its rows), or the product's error."""
    from collections.abc import Mapping as AnyMapping

    from ..engine.core.errors import InvalidArgumentError
    from ..engine.trees.evaluate import TreeTable
    from ..engine.trees.inventory import TreeInventory

    if isinstance(table, (TreeTable, str, os.PathLike)):
        return table
    if isinstance(table, TreeInventory):
        return table.rows()
    if isinstance(table, (list, tuple)) and all(isinstance(r, AnyMapping) for r in table):
        return list(table)
    raise InvalidArgumentError(
        f"{what}: expected a TreeTable, a CSV file's path, rows (a list of dicts with tree_id, x, y) "
        f"or a TreeInventory, got {type(table).__name__}"
    )


def evaluate_into(
    folder: Path, named, field_table, *, by: str, max_distance: float, shown_as: Optional[Path] = None
) -> EvaluationOutcome:
    """Evaluate and write into ``folder`` (inside a transaction); the outcome's ``lines`` name the
    files as they will be (``shown_as``, the folder's final place)."""
    runs = evaluate_runs(named, field_table, by=by, max_distance=max_distance)
    paths = write_evaluation(folder, runs)
    lines, failed = [], []
    for name, ev in runs.items():
        if not ev:  # no tree matched: the reason
            failed.append(f"{name}: {ev.reason}")
            lines.append(f"failed: {failed[-1]}")
        else:
            lines.append(f"{name}: {ev.summary()}")
    lines.append(f"-> {paths['csv']}, report: {paths['html']}")
    final = Path(shown_as) if shown_as is not None else Path(folder)
    lines = [line.replace(str(folder), str(final)) for line in lines]
    paths = {k: final / Path(v).relative_to(folder) for k, v in paths.items()}
    return EvaluationOutcome(
        status="failed" if failed else "ok",
        reason="; ".join(failed),
        out=final,
        runs=runs,
        lines=tuple(lines),
        paths=paths,
    )


def evaluate_files(runs: dict, field_csv) -> dict:
    """Name -> :class:`~forestreg.engine.trees.evaluate.Evaluation` of each tree table
    (``trees.csv``, or a trees folder) against the field records ``field_csv`` (no file written)."""
    from ..engine.trees.evaluate import evaluate

    results = {}
    for name, path in runs.items():
        p = Path(path)
        results[name] = evaluate(p / "trees.csv" if p.is_dir() else p, field_csv)
    return results


# ----------------------------------------------------------------------------- the folder


#: The figures of the wide table (paper table 3 layout), each with its runs side by side.
TABLE_METRICS = ("n", "r2", "rmse", "rrmse_percent", "bias")


def write_evaluation(
    out_dir: Union[str, os.PathLike[str]],
    runs: Mapping[str, Evaluation],
    *,
    title: Optional[str] = None,
) -> dict[str, Path]:
    """Write the evaluation of one or several runs into ``out_dir`` (created if missing).

    Files (each written atomically):

    * ``evaluation.csv``: one row per parameter; per figure (n, r2, rmse, rrmse_percent, bias)
      one column per run, side by side as in the paper's table 3 (``r2_ground, r2_fused, ...``);
      RMSE and bias in the parameter's unit (metres, m², m³);
    * ``detection.csv``: one row per run: field trees, estimated trees, matched, omitted,
      commission and the two rates;
    * ``matches_<run>.csv``: the pairs of each run with both values of every parameter;
    * ``evaluation.json``: all of it;
    * ``figures/scatter_<parameter>.png``: estimate against field value, one colour per run,
      with the 1:1 line;
    * ``report.html``: a self-contained report (:mod:`forestreg.engine.report.evaluation_report`).

    Returns the paths by name ("csv", "detection", "json", "html", "scatter_<parameter>",
    "matches_<run>").
    """
    from ..engine.core.errors import ParameterError
    from ..engine.io.results import file_stem, write_evaluation_files
    from ..engine.report.evaluation_report import scatter_png, write_evaluation_report
    from ..engine.trees.evaluate import PARAMETERS, pair_rows

    if not runs:
        raise ParameterError("no runs to write: give at least one evaluation")
    names = [str(n) for n in runs]
    if any(not n.strip() for n in names):
        raise ParameterError("run names must not be empty")
    stems = [file_stem(n) for n in names]
    if len(set(stems)) != len(stems):
        raise ParameterError(f"run names {names} are not distinct as file names")
    out = Path(out_dir)
    params = _run_parameters(runs)
    tables: dict = {
        "evaluation": (_wide_rows(runs, params), None),
        "detection": ([{"run": name, **ev.detection.to_dict()} for name, ev in runs.items()], None),
    }
    for (name, ev), stem in zip(runs.items(), stems):
        tables[f"matches_{stem}"] = (pair_rows(ev), ["field_id", "estimated_id", "distance_m"])
    doc = {
        "definitions": {
            "r2": "1 - SS_res/SS_tot, SS_res = sum (estimate - field)^2, SS_tot = sum (field - mean field)^2",
            "rmse": "sqrt(mean (estimate - field)^2), in the parameter's unit",
            "rrmse_percent": "100 * RMSE / mean field value",
            "bias": "mean (estimate - field)",
            "omitted": "field trees with no estimated tree",
            "commission": "estimated trees with no field tree",
        },
        "units": {p: PARAMETERS[p].unit for p in params},
        "runs": {name: ev.to_dict() for name, ev in runs.items()},
    }
    figures: dict[str, bytes] = {}
    for p in params:
        png = scatter_png(runs, p)
        if png is not None:
            figures[p] = png
    paths = write_evaluation_files(out, tables, doc, {f"scatter_{p}": png for p, png in figures.items()})
    paths["csv"] = paths.pop("evaluation")
    paths["html"] = out / "report.html"
    write_evaluation_report(paths["html"], runs, title=title, figures=figures)
    return paths


def _run_parameters(runs: Mapping[str, Evaluation]) -> list[str]:
    from ..engine.trees.evaluate import PARAMETERS

    present = {p for ev in runs.values() for p in ev.stats}
    return [p for p in PARAMETERS if p in present]


def _wide_rows(runs: Mapping[str, Evaluation], params: Sequence[str]) -> list[dict[str, Any]]:
    from ..engine.trees.evaluate import PARAMETERS

    rows = []
    for p in params:
        info = PARAMETERS[p]
        row: dict[str, Any] = {"parameter": p, "label": info.label, "unit": info.unit}
        for metric in TABLE_METRICS:
            for name, ev in runs.items():
                s = ev.stats.get(p)
                row[f"{metric}_{name}"] = (s.n if metric == "n" else getattr(s, metric)) if s is not None else None
        rows.append(row)
    return rows
