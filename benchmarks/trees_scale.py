"""Benchmark: trees at scale -- ``forestreg trees`` on a ~30 M-point merged plot beside Sylva's
``ground`` + ``trees`` and beside only reading the file, with the accuracy against the
simulator's truth at that density and at the plot's own.

The case: the plot of :mod:`benchmarks.trees_speed` (a simulated ``mixed_temperate`` plot, 26 m
square, five TLS scans at 0.19 deg merged: 2.9 M points, 59 true trees), and the same plot
densified ``--copies`` times (default 11: 32 M points) as :func:`benchmarks.big_scan.densify`
does it (each copy of every point moved by up to 2 mm; the trees, and so the truth, are the
same). Both clouds are made once and kept in the work folder (``--workdir``, default
``bench_out/trees_scale``).

Commands on each cloud, in turn, each a child process under
:func:`benchmarks.peers.run_command` (wall time and peak memory):

* reading the file (``read_scan``, x, y, z as ``forestreg trees`` reads them);
* ``forestreg trees IN --out DIR --no-cylinders --no-report``: stems, DBH, heights, crowns;
* ``forestreg trees IN --out DIR --no-report``: the same with the cylinder models (volume); the
  cylinder models' own seconds are its leaf-wood separation (their input) and its ``trees`` step
  less that of the run without them;
* Sylva (PyPI ``sylva-rs``): ``sylva ground IN NORM`` then ``sylva trees NORM -o trees.csv``
  (the two commands' seconds added, the larger peak).

Accuracy over the true trees within 11 m of the centre with DBH >= 0.1 m (as
:mod:`benchmarks.trees_compare`): found (a stem within 0.5 m), false stems, DBH rRMSE, height
rRMSE of every matched tree and of forestreg's unflagged heights. Run from the repository root:
``python -m benchmarks.trees_scale [--copies 11] [--workdir DIR] [--json FILE]`` (about 10
minutes on 2 cores; or ``benchmarks/run.py --only treescale``).
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
from pathlib import Path
from typing import Any, Optional

if __package__:
    from . import big_scan, trees_compare, trees_speed
    from .peers import run_command, show_rows, sylva_command
else:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import big_scan  # type: ignore[no-redef]
    import trees_compare  # type: ignore[no-redef]
    import trees_speed  # type: ignore[no-redef]
    from peers import run_command, show_rows, sylva_command  # type: ignore[no-redef]

OUT = Path("bench_out") / "trees_scale"
COPIES = 11
_READ = "import sys; from forestreg.engine.io import read_scan; print(len(read_scan(sys.argv[1], with_intensity=False).points))"
_STEP = re.compile(r"^\s+([a-z_]+): ([0-9.]+) s$")


def clouds(workdir: Path, copies: int = COPIES) -> tuple[list[tuple[str, Path]], list[dict[str, Any]]]:
    """[(label, LAZ path)] of the plot and of its densified copy, and the true trees; made when missing."""
    base = workdir / "base"
    trees_speed.load_case(base)
    dense = workdir / f"plot_x{copies}.laz"
    if not dense.exists():
        partial = dense.with_suffix(".part.laz")
        big_scan.densify(base / "plot.laz", partial, copies)
        partial.replace(dense)
    truth = json.loads((base / "truth.json").read_text())["trees"]
    return [("plot", base / "plot.laz"), (f"plot x{copies}", dense)], truth


def _points(path: Path) -> int:
    import laspy

    with laspy.open(str(path)) as f:
        return int(f.header.point_count)


def _steps(log: Path) -> dict[str, float]:
    """The step timings ``forestreg trees`` printed (``  name: 1.2 s`` lines)."""
    out: dict[str, float] = {}
    if log.exists():
        for line in re.split(r"[\r\n]+", log.read_text(errors="replace")):
            m = _STEP.match(line)
            if m:
                out[m.group(1)] = float(m.group(2))
    return out


def _forestreg(cloud: Path, work: Path, tag: str, cylinders: bool) -> dict[str, Any]:
    out, log = work / f"fr_{tag}", work / f"fr_{tag}.log"
    argv = [sys.executable, "-m", "forestreg.cli", "trees", str(cloud), "--out", str(out), "--no-report"]
    run = run_command(argv + ([] if cylinders else ["--no-cylinders"]), log=log)
    rows = trees_compare._rows(out / "trees.csv") if run.status == 0 else []
    return {
        "wall_s": run.wall_s,
        "peak_mb": max(run.peak_mb, run.tree_mb if math.isfinite(run.tree_mb) else 0.0),
        "status": run.status,
        "steps": _steps(log),
        "rows": rows,
    }


def run(workdir: Optional[Path] = None, copies: int = COPIES) -> list[dict[str, Any]]:
    """One row per cloud: reading, forestreg without and with cylinder models, Sylva, accuracy."""
    work = Path(workdir or OUT)
    work.mkdir(parents=True, exist_ok=True)
    cases, truth = clouds(work, copies)
    sylva = sylva_command()
    rows: list[dict[str, Any]] = []
    for label, cloud in cases:
        tag = cloud.stem
        row: dict[str, Any] = {"case": label, "points": _points(cloud), "load_1min": os.getloadavg()[0]}
        read = run_command([sys.executable, "-c", _READ, str(cloud)])
        row["read"] = {"wall_s": read.wall_s, "peak_mb": read.peak_mb, "status": read.status}
        fast = _forestreg(cloud, work, f"{tag}_nocyl", cylinders=False)
        full = _forestreg(cloud, work, f"{tag}_cyl", cylinders=True)
        for key, res in (("forestreg", fast), ("forestreg_cylinders", full)):
            rows_ = res.pop("rows")
            row[key] = {
                **res,
                **trees_compare._plot_figures(
                    rows_, truth, dbh_key="dbh_m", height_key="height_m", flagged=trees_compare._height_low
                ),
            }
        row["cylinder_s"] = (
            full["steps"].get("leafwood", 0.0)
            + full["steps"].get("trees", math.nan)
            - fast["steps"].get("trees", math.nan)
        )
        if sylva:
            res, sy = trees_compare._sylva_trees(sylva, cloud, work)
            row["sylva"] = {**res, **trees_compare._plot_figures(sy, truth, dbh_key="dbh", height_key="height")}
        rows.append(row)
    return rows


def _f(v: Any, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def _ratio(a: dict[str, Any], b: Optional[dict[str, Any]], key: str = "wall_s") -> str:
    if not b or not a or a.get("status") or b.get("status"):
        return "-"
    return _f(a[key] / b[key], ".2f") + "x"


def _accuracy(r: dict[str, Any]) -> str:
    text = (
        f"{r['found']}/{r['true']} ({r['false_stems']}), DBH {_f(r['dbh_rrmse_pct'], '.1f')} %, "
        f"height {_f(r['height_rrmse_pct'], '.1f')} %"
    )
    if "heights_unflagged" in r:
        text += f" (unflagged {r['heights_unflagged']}: {_f(r['unflagged_height_rrmse_pct'], '.1f')} %)"
    return text


def format_rows(rows: list[dict[str, Any]]) -> str:
    """Two Markdown tables: time and memory with the ratios, then the accuracy against the truth."""
    lines = [
        "Trees at scale (one run; seconds and peak MB of each command; forestreg without cylinder models: "
        "stems, DBH, heights, crowns; cylinder models: their leaf-wood separation and fits)",
        "",
        "| cloud | points | reading | forestreg | Sylva ground + trees | forestreg / Sylva | forestreg / reading "
        "| peak, forestreg / Sylva | with cylinder models | cylinder models | 1-min load |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        fr, fc, sy, rd = r["forestreg"], r["forestreg_cylinders"], r.get("sylva"), r["read"]
        lines.append(
            f"| {r['case']} | {r['points'] / 1e6:.1f} M | {_f(rd['wall_s'], '.1f')} s | {_f(fr['wall_s'], '.1f')} s, {_f(fr['peak_mb'], ',.0f')} MB "
            f"| {_f(sy['wall_s'], '.1f') + ' s, ' + _f(sy['peak_mb'], ',.0f') + ' MB' if sy else '-'} | {_ratio(fr, sy)} | {_ratio(fr, rd)} "
            f"| {_ratio(fr, sy, 'peak_mb')} | {_f(fc['wall_s'], '.1f')} s, {_f(fc['peak_mb'], ',.0f')} MB | {_f(r['cylinder_s'], '.1f')} s "
            f"| {r['load_1min']:.1f} |"
        )
    lines += [
        "",
        "forestreg's steps without cylinder models (s): "
        + "; ".join(
            f"{r['case']}: " + ", ".join(f"{k} {v:.1f}" for k, v in r["forestreg"]["steps"].items()) for r in rows
        ),
        "",
        "Against the truth (found/true (false stems), DBH rRMSE, height rRMSE):",
        "",
        "| cloud | forestreg | forestreg with cylinder models | Sylva |",
        "|---|---|---|---|",
    ]
    for r in rows:
        sy = r.get("sylva")
        lines.append(
            f"| {r['case']} | {_accuracy(r['forestreg'])} | {_accuracy(r['forestreg_cylinders'])} | {_accuracy(sy) if sy else '-'} |"
        )
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--copies", type=int, default=COPIES, help="copies of the plot in the dense cloud (default 11: 32 M points)"
    )
    ap.add_argument(
        "--workdir", type=Path, help="keep the clouds and every command's output here (default bench_out/trees_scale)"
    )
    ap.add_argument("--json", type=Path, help="also write the rows to this JSON file")
    args = ap.parse_args(argv)
    rows = run(args.workdir, args.copies)
    return show_rows(format_rows(rows), rows, args.json, indent=1, default=float)


if __name__ == "__main__":
    sys.exit(main())
