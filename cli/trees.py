"""``forestreg trees`` and ``forestreg evaluate``: tree measurements and their check against field
records (System B)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional, Sequence

from .common import Reporter, add_crs_option, add_units_params, number, product_params, run_outcome, say, shown


def add_parsers(sub) -> None:
    p = sub.add_parser(
        "trees", help="detect and measure trees (DBH, height, crown, cylinder models) in a ground-based or fused cloud"
    )
    p.add_argument("cloud", help="the cloud (LAS/LAZ/PLY/E57/...), ground included")
    p.add_argument(
        "--out",
        required=True,
        help="output folder (trees.csv, stem_curves.csv, cylinders/, report.html); replaced when the run completes",
    )
    p.add_argument("--transform", help="move the cloud first (transform.txt of `coregister`: into the UAV/field frame)")
    p.add_argument("--field", help="field records CSV: evaluate the trees against them into OUT/evaluation")
    p.add_argument(
        "--no-cylinders",
        action="store_true",
        help="skip the cylinder models and the leaf-wood separation they are fitted on (faster; no volume, no wood fraction)",
    )
    p.add_argument(
        "--single-tree",
        nargs="?",
        const="yes",
        choices=("auto", "yes", "no"),
        help="the cloud is one tree (TreeQSM/AdTree-style, little or no ground): one tree, its height the cloud's "
        "top above its base; 'no' for a plot; default: decided from the cloud",
    )
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    add_crs_option(p, "layers.gpkg is in it (with --transform, the co-registration's result.json names the target's)")
    add_units_params(p, "units of the input coordinates", cmd_trees)

    p = sub.add_parser(
        "evaluate", help="compare trees.csv with field records: R2, RMSE, rRMSE per parameter (paper table 3)"
    )
    p.add_argument("trees", help="trees.csv of `forestreg trees`")
    p.add_argument("field", help="field records CSV (tree_id, x, y and any of dbh_m/dbh_cm, height_m, ...)")
    p.add_argument(
        "--out",
        required=True,
        help="output folder (evaluation.csv/.json, figures, report.html); replaced when the run completes",
    )
    p.add_argument("--name", help="name of the first run (default: its folder name)")
    p.add_argument(
        "--also",
        action="append",
        metavar="[NAME=]TREES",
        help="another run to show side by side, e.g. fused=fused/trees.csv",
    )
    p.add_argument("--by", choices=("position", "id"), default="position", help="match trees by position or by id")
    p.add_argument(
        "--max-distance",
        type=number("--max-distance", positive=True),
        default=1.0,
        help="largest distance of a position match, m (default 1)",
    )
    p.set_defaults(func=cmd_evaluate, long_running=False)


def cmd_trees(args: argparse.Namespace) -> int:
    params = product_params(args).trees
    if getattr(args, "single_tree", None):
        params = params.replace(single_tree=params.single_tree.replace(mode=args.single_tree))
    return run_trees(
        args.cloud,
        args.out,
        transform=args.transform,
        field=args.field,
        units=args.units,
        params=params,
        cylinders=not args.no_cylinders,
        report=not args.no_report,
        reporter=args.reporter,
        crs=args.crs,
    )


def run_trees(
    cloud_path,
    out,
    *,
    transform=None,
    field=None,
    units: str = "m",
    cylinders: bool = True,
    report: bool = True,
    params=None,
    reporter: Optional[Reporter] = None,
    crs=None,
) -> int:
    """Measure the trees of ``cloud_path`` into the folder ``out``
    (:func:`forestreg.app.trees.measure_trees_file`) and print the outcome."""
    from ..app.trees import measure_trees_file

    reporter = reporter or Reporter("none", "trees")
    outcome = run_outcome(
        reporter,
        measure_trees_file,
        cloud_path,
        out,
        params,
        transform=transform,
        field=field,
        units=units,
        cylinders=cylinders,
        report=report,
        crs=crs,
    )
    return print_trees(outcome, reporter, units)


def print_trees(outcome, reporter: Reporter, units: str = "m") -> int:
    """The lines of a trees run's outcome; returns the exit code."""
    out = outcome.out
    if not outcome and outcome.evaluation is None:  # no tree: nothing written
        say(f"failed: {outcome.reason}", argparse.Namespace(reporter=reporter), err=True)
        return 1
    reporter.done("", out / "trees.csv")
    quiet = argparse.Namespace(reporter=reporter)
    for step, seconds in outcome.timings.items():  # the steps run, in order
        say(f"  {step.removesuffix('_s')}: {seconds:.1f} s", quiet)
    unit_note = "" if units == "m" else f" (positions in {units}, sizes in metres)"
    inventory = outcome.result
    stations = getattr(inventory, "stations", None)
    if stations is not None and len(stations.positions):
        say(f"  {stations.describe()}", quiet)
    if inventory.method == "single":
        say(f"  single-tree cloud: {inventory.single_tree_reason}", quiet)
        if getattr(inventory, "single_tree_warning", ""):
            say(f"warning: {inventory.single_tree_warning}", quiet, err=True)
    say(f"{outcome.line()}{unit_note} -> {shown(out) / 'trees.csv'}", quiet)
    if outcome.report is not None:
        print(f"report: {shown(out) / 'report.html'}")
    if outcome.evaluation is not None:
        for line in outcome.evaluation.lines:
            print(line.replace(str(out), str(shown(out))))
        return 0 if outcome.evaluation else 1
    return 0


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


def run_evaluate(
    named: Sequence[tuple[str, str | Path]],
    field,
    out,
    *,
    by: str = "position",
    max_distance: float = 1.0,
    reporter: Optional[Reporter] = None,
) -> int:
    """Evaluate the named tree tables against ``field`` into the folder ``out``
    (:func:`forestreg.app.evaluation.evaluate_tables`) and print the outcome."""
    from ..app.evaluation import evaluate_tables

    reporter = reporter or Reporter("none", "evaluate")
    outcome = evaluate_tables(named, field, out, by=by, max_distance=max_distance, progress=reporter)
    return print_evaluate(outcome, reporter)


def print_evaluate(outcome, reporter: Reporter) -> int:
    """The lines of an evaluation's outcome; returns the exit code."""
    out = outcome.out
    reporter.done("", out / "evaluation.json")
    ns = argparse.Namespace(reporter=reporter)
    for line in outcome.lines:
        say(line.replace(str(out), str(shown(out))), ns, err=line.startswith("failed"))
    return 0 if outcome else 1
