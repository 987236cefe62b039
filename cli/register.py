"""``forestreg register``: one TLS pair from trunk shadows (System A)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional, Sequence

from ..engine.core.uncertainty import evidence_notes
from .common import (
    PARAMS_HELP,
    UNITS,
    Reporter,
    add_crs_option,
    direction,
    file_section,
    floats,
    number,
    offsets,
    params_from_args,
    run_outcome,
    say,
    shown,
)


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("register", help="register a moving scan onto a reference scan from trunk shadows")
    p.add_argument("reference", help="reference scan (LAS/LAZ/PLY/PCD/E57/XYZ)")
    p.add_argument("moving", help="moving scan, mapped onto the reference")
    p.add_argument(
        "--out",
        required=True,
        help="output folder (new, empty, or an earlier register output: it is replaced when the run completes)",
    )
    p.add_argument("--dr", type=number("--dr", positive=True), help="VOP radius D_r in metres (default: automatic)")
    p.add_argument("--dc", type=number("--dc", positive=True), help="reduction radius D_c in metres (default 30)")
    p.add_argument("--dh", type=offsets, help="slice offsets dh in metres, comma-separated (default 0)")
    p.add_argument("--params", help=PARAMS_HELP)
    p.add_argument(
        "--scanner-position",
        action="append",
        type=lambda s: floats(s, 3, "--scanner-position"),
        metavar="X,Y,Z",
        help="scanner position in file coordinates: first for the reference, again for the moving scan (default: each file's origin)",
    )
    p.add_argument(
        "--units",
        choices=sorted(UNITS),
        default="m",
        help="unit of the files' coordinates (default m); results are written in the same unit",
    )
    p.add_argument(
        "--up",
        action="append",
        type=direction("--up"),
        metavar="X,Y,Z",
        help="the true vertical in a scan's own coordinates (from its inclination sensor): first for the reference, again for the moving scan (default: estimated from the data)",
    )
    p.add_argument(
        "--write-registered",
        action="store_true",
        help="also write the moving scan transformed into the reference frame (LAZ)",
    )
    add_crs_option(p, "result.json and the registered scan are in the reference scan's frame and take its CRS")
    p.set_defaults(func=cmd_register, long_running=True)
    return p


def cmd_register(args: argparse.Namespace) -> int:
    return run_register(
        args.reference,
        args.moving,
        args.out,
        params=params_from_args(args),
        positions=args.scanner_position or [],
        ups=args.up or [],
        units=args.units,
        write_registered=args.write_registered,
        reporter=args.reporter,
        scanner_params=file_section(args, "scanner_position"),
        crs=args.crs,
    )


def run_register(
    reference_path: str | Path,
    moving_path: str | Path,
    out: str | Path,
    *,
    params=None,
    positions: Sequence = (),
    ups: Sequence = (),
    units: str = "m",
    write_registered: bool = False,
    reporter: Optional[Reporter] = None,
    scanner_params=None,
    crs=None,
) -> int:
    """Register ``moving_path`` onto ``reference_path`` into the output folder ``out``
    (:func:`forestreg.app.pair.register_pair`) and print the outcome. Returns the exit code (0 ok,
    1 failed with a reason)."""
    from ..app.pair import register_pair

    reporter = reporter or Reporter("none", "register")
    return print_register(
        run_outcome(
            reporter,
            register_pair,
            reference_path,
            moving_path,
            out,
            params,
            positions=positions,
            ups=ups,
            units=units,
            write_registered=write_registered,
            scanner_params=scanner_params,
            crs=crs,
        ),
        reporter,
    )


def print_register(outcome, reporter: Reporter) -> int:
    """The lines of a pair registration's outcome; returns the exit code."""
    out = outcome.out
    reporter.done("", out / "result.json")
    ns = argparse.Namespace(reporter=reporter)
    if outcome:
        result = outcome.result
        icp = result.icp
        for note in evidence_notes(result.uncertainty):  # before the last line, which is the result's
            say(f"uncertainty: {note}", ns)
        say(
            f"ok: {result.matched} matched VOPs ({result.reference_vops} / {result.moving_vops}), "
            f"ICP std {1000 * icp.std_m:.1f} mm, fitness {icp.fitness:.2f} -> {shown(out) / 'result.json'}",
            ns,
        )
        if outcome.figure is not None:
            print(f"figure: {shown(out) / 'registration.png'}")
        return 0
    say(f"failed: {outcome.reason} -> {shown(out) / 'result.json'}", ns, err=True)
    return 1
