"""Evaluation: measured trees against field records (R², RMSE, rRMSE per parameter, detection
rates; the paper's table 3).

:func:`evaluate_tables` reads the tree tables and the field records, matches and scores them
(:func:`forestreg.engine.trees.evaluate.evaluate`) and writes the output folder
(``evaluation.csv``/``.json``, ``detection.csv``, figures, ``report.html``) as one transaction.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

from .common import RunOutcome


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


def evaluate_tables(named: Sequence[tuple[str, str | Path]], field_path, out: str | Path, *, by: str = "position",
                    max_distance: float = 1.0, progress=None, cancel=None) -> EvaluationOutcome:
    """Evaluate the named tree tables (``[(name, trees.csv), ...]``) against ``field_path`` into
    the folder ``out`` (a transaction)."""
    from ..engine.core.atomic import check_output_folder, output_folder
    from ..engine.trees.evaluate import read_tree_table

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
    from ..engine.trees.evaluate import evaluate

    return {name: evaluate(table, field_table, by=by, max_distance_m=max_distance) for name, table in named}


def evaluate_into(folder: Path, named, field_table, *, by: str, max_distance: float, shown_as: Optional[Path] = None) -> EvaluationOutcome:
    """Evaluate and write into ``folder`` (inside a transaction); the outcome's ``lines`` name the
    files as they will be (``shown_as``, the folder's final place)."""
    from ..engine.io.evaluation import write_evaluation

    runs = evaluate_runs(named, field_table, by=by, max_distance=max_distance)
    paths = write_evaluation(folder, runs)
    lines, failed = [], []
    for name, ev in runs.items():
        d = ev.detection
        figures = ", ".join(
            f"{p} R2 {st.r2:.2f} rRMSE {st.rrmse_percent:.1f} %" for p, st in ev.stats.items() if st.n >= 2
        )
        if d.matched == 0:
            how = "no shared tree ids" if by == "id" else f"no tree within {max_distance:g} m of a field tree (same coordinates and units?)"
            failed.append(f"{name}: 0 of {d.field_trees} field trees matched ({how})")
            lines.append(f"failed: {failed[-1]}")
        else:
            lines.append(f"{name}: {d.matched} of {d.field_trees} field trees matched; {figures}")
    lines.append(f"-> {paths['csv']}, report: {paths['html']}")
    final = Path(shown_as) if shown_as is not None else Path(folder)
    lines = [line.replace(str(folder), str(final)) for line in lines]
    paths = {k: final / Path(v).relative_to(folder) for k, v in paths.items()}
    return EvaluationOutcome(status="failed" if failed else "ok", reason="; ".join(failed), out=final, runs=runs,
                             lines=tuple(lines), paths=paths)


def evaluate_files(runs: dict, field_csv) -> dict:
    """Name -> :class:`~forestreg.engine.trees.evaluate.Evaluation` of each tree table
    (``trees.csv``, or a trees folder) against the field records ``field_csv`` (no file written)."""
    from ..engine.trees.evaluate import evaluate

    results = {}
    for name, path in runs.items():
        p = Path(path)
        results[name] = evaluate(p / "trees.csv" if p.is_dir() else p, field_csv)
    return results
