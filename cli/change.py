"""``forestreg change``: two surveys of one plot years apart, registered on what persisted and
compared tree by tree (persisting, removed, new; DBH and height growth)."""

from __future__ import annotations

import argparse

from ..app.units import UNITS
from .common import Reporter, add_crs_option, add_units_params, product_params, say, shown


def add_parsers(sub) -> None:
    p = sub.add_parser(
        "change",
        help="compare two surveys of one plot (re-survey): register AFTER onto BEFORE from the persisting stems, "
        "then persisting / removed / new trees with DBH and height growth",
        description="BEFORE and AFTER are each a merged ground-based cloud (TLS, MLS, backpack; any frame), a saved plot "
        "project (.json) or the trees.csv (or output folder) of 'forestreg trees'.",
    )
    p.add_argument("before", help="the earlier survey: a cloud, a project file or a trees.csv")
    p.add_argument("after", help="the later survey: a cloud, a project file or a trees.csv")
    p.add_argument(
        "--out",
        required=True,
        help="output folder (result.json, tree_changes.csv, report.html); replaced when the run completes",
    )
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    add_crs_option(p, "result.json and layers.gpkg are in BEFORE's frame and take its CRS")
    add_units_params(p, "unit of both surveys' coordinates", cmd_change)
    for role in ("before", "after"):
        p.add_argument(
            f"--units-{role}",
            choices=sorted(UNITS),
            default=None,
            help=f"unit of the {role.upper()} survey's coordinates, when the two differ (default: --units)",
        )


def cmd_change(args: argparse.Namespace) -> int:
    from ..app.change import detect_change_files

    reporter: Reporter = args.reporter
    try:
        outcome = detect_change_files(
            args.before,
            args.after,
            args.out,
            product_params(args),
            units=args.units,
            units_before=args.units_before,
            units_after=args.units_after,
            report=not args.no_report,
            crs=args.crs,
            progress=reporter,
        )
    finally:
        reporter.close()
    out = outcome.out
    reporter.done("" if outcome.ok else outcome.reason, out / "result.json")
    ns = argparse.Namespace(reporter=reporter)
    for note in outcome.notes:
        print(f"note: {note}")
    if outcome.ok:
        say(f"ok: {outcome.line()} -> {shown(out) / 'tree_changes.csv'}", ns)
        if (out / "report.html").exists():
            print(f"report: {shown(out) / 'report.html'}")
        return 0
    say(f"failed: {outcome.reason} -> {shown(out) / 'result.json'}", ns, err=True)
    return 1
