"""``forestreg trees`` and ``forestreg evaluate``: tree measurements and their check against field
records (System B)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional, Sequence

from .common import UNITS, Reporter, add_units_params, number, product_params, say, shown


def add_parsers(sub) -> None:
    p = sub.add_parser("trees", help="detect and measure trees (DBH, height, crown, cylinder models) in a ground-based or fused cloud")
    p.add_argument("cloud", help="the cloud (LAS/LAZ/PLY/E57/...), ground included")
    p.add_argument("--out", required=True, help="output folder (trees.csv, stem_curves.csv, cylinders/, report.html); replaced when the run completes")
    p.add_argument("--transform", help="move the cloud first (transform.txt of `coregister`: into the UAV/field frame)")
    p.add_argument("--field", help="field records CSV: evaluate the trees against them into OUT/evaluation")
    p.add_argument("--no-cylinders", action="store_true", help="skip the cylinder models (faster; no volume)")
    p.add_argument("--single-tree", nargs="?", const="yes", choices=("auto", "yes", "no"),
                   help="the cloud is one tree (TreeQSM/AdTree-style, little or no ground): one tree, its height the cloud's "
                        "top above its base; 'no' for a plot; default: decided from the cloud")
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    add_units_params(p, "units of the input coordinates", cmd_trees)

    p = sub.add_parser("evaluate", help="compare trees.csv with field records: R2, RMSE, rRMSE per parameter (paper table 3)")
    p.add_argument("trees", help="trees.csv of `forestreg trees`")
    p.add_argument("field", help="field records CSV (tree_id, x, y and any of dbh_m/dbh_cm, height_m, ...)")
    p.add_argument("--out", required=True, help="output folder (evaluation.csv/.json, figures, report.html); replaced when the run completes")
    p.add_argument("--name", help="name of the first run (default: its folder name)")
    p.add_argument("--also", action="append", metavar="[NAME=]TREES", help="another run to show side by side, e.g. fused=fused/trees.csv")
    p.add_argument("--by", choices=("position", "id"), default="position", help="match trees by position or by id")
    p.add_argument("--max-distance", type=number("--max-distance", positive=True), default=1.0, help="largest distance of a position match, m (default 1)")
    p.set_defaults(func=cmd_evaluate, long_running=False)


def cmd_trees(args: argparse.Namespace) -> int:
    params = product_params(args).trees
    if getattr(args, "single_tree", None):
        params = params.replace(single_tree=params.single_tree.replace(mode=args.single_tree))
    return run_trees(args.cloud, args.out, transform=args.transform, field=args.field, units=args.units, params=params,
                     cylinders=not args.no_cylinders, report=not args.no_report, reporter=args.reporter)


def run_trees(cloud_path, out, *, transform=None, field=None, units: str = "m", cylinders: bool = True,
              report: bool = True, params=None, reporter: Optional[Reporter] = None) -> int:
    """Measure the trees of ``cloud_path`` into the folder ``out`` (a transaction), with
    ``field`` also evaluated into ``out/evaluation``."""
    import dataclasses

    from ..engine.core.atomic import check_output_folder, output_folder
    from ..engine.core.transform import read_matrix, to_metres
    from ..engine.io import read_scan
    from ..engine.io.base import check_readable
    from ..engine.trees.evaluate import read_tree_table
    from ..engine.trees.inventory import TreeParams, measure_trees

    reporter = reporter or Reporter("none", "trees")
    scale = UNITS[units]
    check_readable(cloud_path)
    out = check_output_folder(out, "trees", inputs=[cloud_path, transform, field])
    matrix = to_metres(read_matrix(transform), scale) if transform else None
    field_table = read_tree_table(field) if field else None  # checked before the work
    cloud = read_scan(cloud_path, unit_scale=scale, with_intensity=False)  # the trees use x, y, z alone
    if matrix is not None:
        cloud = cloud.transformed(matrix)
    params = params or TreeParams()
    if not cylinders:
        params = dataclasses.replace(params, cylinder_models=False)
    try:
        inventory = measure_trees(cloud.points, params, progress=reporter, origin_shift=cloud.origin_shift)
    finally:
        reporter.close()
    with output_folder(out, "trees") as tmp:
        inventory.write(tmp, cloud.points, report=report, unit_scale=scale)
        code = 0
        if field_table is not None:
            code, lines = _evaluate_into(tmp / "evaluation", [("trees", read_tree_table(tmp / "trees.csv"))], field_table,
                                         by="position", max_distance=1.0 / scale)
    reporter.done("", out / "trees.csv")
    quiet = argparse.Namespace(reporter=reporter)
    for step, seconds in inventory.timings.items():  # the steps run, in order
        say(f"  {step.removesuffix('_s')}: {seconds:.1f} s", quiet)
    unit_note = "" if units == "m" else f" (positions in {units}, sizes in metres)"
    if inventory.method == "single":
        say(f"  single-tree cloud: {inventory.single_tree_reason}", quiet)
    say(f"{inventory.summary()}{unit_note} -> {shown(out) / 'trees.csv'}", quiet)
    if report and (out / "report.html").exists():
        print(f"report: {shown(out) / 'report.html'}")
    if field_table is not None:
        for line in lines:
            print(line.replace(str(tmp), str(shown(out))))
    return code


def cmd_evaluate(args: argparse.Namespace) -> int:
    from ..engine.core.errors import UsageError

    named = [(args.name or Path(args.trees).parent.name or "run", args.trees)]
    for item in args.also or []:
        name, sep, path = item.partition("=")
        if not sep:
            name, path = Path(item).parent.name or f"run{len(named) + 1}", item
        named.append((name, path))
    if len({n for n, _ in named}) != len(named):
        raise UsageError("two runs have the same name: name them with --name and --also NAME=PATH")
    return run_evaluate(named, args.field, args.out, by=args.by, max_distance=args.max_distance, reporter=args.reporter)


def run_evaluate(named: Sequence[tuple[str, str | Path]], field, out, *, by: str = "position", max_distance: float = 1.0,
                 reporter: Optional[Reporter] = None) -> int:
    """Evaluate the named tree tables against ``field`` into the folder ``out`` (a transaction)."""
    from ..engine.core.atomic import check_output_folder, output_folder
    from ..engine.trees.evaluate import read_tree_table

    reporter = reporter or Reporter("none", "evaluate")
    out = check_output_folder(out, "evaluate", inputs=[field, *[p for _, p in named]])
    field_table = read_tree_table(field)
    tables = [(name, read_tree_table(path)) for name, path in named]  # every table checked before the work
    with output_folder(out, "evaluate") as tmp:
        code, lines = _evaluate_into(tmp, tables, field_table, by=by, max_distance=max_distance)
    reporter.done("", out / "evaluation.json")
    ns = argparse.Namespace(reporter=reporter)
    for line in lines:
        say(line.replace(str(tmp), str(shown(out))), ns, err=line.startswith("failed"))
    return code


def _evaluate_into(folder: Path, named, field_table, *, by: str, max_distance: float) -> tuple[int, list[str]]:
    """Evaluate and write; returns the exit code (1 when no tree could be matched) and the lines to print."""
    from ..engine.io.evaluation import write_evaluation
    from ..engine.trees.evaluate import evaluate

    runs = {name: evaluate(table, field_table, by=by, max_distance_m=max_distance) for name, table in named}
    paths = write_evaluation(folder, runs)
    lines, code = [], 0
    for name, ev in runs.items():
        d = ev.detection
        figures = ", ".join(
            f"{p} R2 {st.r2:.2f} rRMSE {st.rrmse_percent:.1f} %" for p, st in ev.stats.items() if st.n >= 2
        )
        if d.matched == 0:
            code = 1
            how = "no shared tree ids" if by == "id" else f"no tree within {max_distance:g} m of a field tree (same coordinates and units?)"
            lines.append(f"failed: {name}: 0 of {d.field_trees} field trees matched ({how})")
        else:
            lines.append(f"{name}: {d.matched} of {d.field_trees} field trees matched; {figures}")
    lines.append(f"-> {paths['csv']}, report: {paths['html']}")
    return code, lines
