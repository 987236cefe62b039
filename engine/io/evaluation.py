"""Writing an evaluation against field records (the files of ``forestreg evaluate``): the wide
CSV in the layout of the paper's table 3, detection rates, matched pairs, JSON, scatter figures
and the HTML report. The figures themselves come from :mod:`..report.evaluation_report`."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from ..core.atomic import atomic_path, write_text_atomic
from ..core.errors import ParameterError
from ..report.evaluation_report import scatter_png, write_evaluation_report
from ..trees.evaluate import PARAMETERS, Evaluation, pair_rows

__all__ = ["TABLE_METRICS", "write_evaluation"]



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
    if not runs:
        raise ParameterError("no runs to write: give at least one evaluation")
    names = [str(n) for n in runs]
    if any(not n.strip() for n in names):
        raise ParameterError("run names must not be empty")
    stems = [_file_stem(n) for n in names]
    if len(set(stems)) != len(stems):
        raise ParameterError(f"run names {names} are not distinct as file names")
    out = Path(out_dir)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    params = _run_parameters(runs)
    paths: dict[str, Path] = {}

    paths["csv"] = out / "evaluation.csv"
    write_text_atomic(paths["csv"], _csv_text(_wide_rows(runs, params)))
    paths["detection"] = out / "detection.csv"
    det_rows = [{"run": name, **ev.detection.to_dict()} for name, ev in runs.items()]
    write_text_atomic(paths["detection"], _csv_text(det_rows))
    for (name, ev), stem in zip(runs.items(), stems):
        key = f"matches_{stem}"
        paths[key] = out / f"{key}.csv"
        write_text_atomic(paths[key], _csv_text(pair_rows(ev), empty_header=["field_id", "estimated_id", "distance_m"]))
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
    paths["json"] = out / "evaluation.json"
    write_text_atomic(paths["json"], json.dumps(doc, indent=2, ensure_ascii=False) + "\n")
    figures: dict[str, bytes] = {}
    for p in params:
        png = scatter_png(runs, p)
        if png is None:
            continue
        figures[p] = png
        key = f"scatter_{p}"
        paths[key] = out / "figures" / f"{key}.png"
        with atomic_path(paths[key]) as tmp:
            tmp.write_bytes(png)
    paths["html"] = out / "report.html"
    write_evaluation_report(paths["html"], runs, title=title, figures=figures)
    return paths


def _run_parameters(runs: Mapping[str, Evaluation]) -> list[str]:
    present = {p for ev in runs.values() for p in ev.stats}
    return [p for p in PARAMETERS if p in present]


def _wide_rows(runs: Mapping[str, Evaluation], params: Sequence[str]) -> list[dict[str, Any]]:
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


def _csv_text(rows: Sequence[Mapping[str, Any]], empty_header: Optional[Sequence[str]] = None) -> str:
    buf = io.StringIO()
    header = list(rows[0].keys()) if rows else list(empty_header or [])
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    for r in rows:
        writer.writerow([_csv_cell(r.get(h)) for h in header])
    return buf.getvalue()


def _csv_cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (float, np.floating)):
        return "" if not math.isfinite(float(value)) else f"{float(value):.6g}"
    if isinstance(value, (np.integer,)):
        return str(int(value))
    return str(value)


def _file_stem(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name.strip()) or "run"
