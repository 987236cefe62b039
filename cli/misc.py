"""``forestreg simulate``, ``demo``, ``gui`` and ``params``."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from .common import Reporter, floats, number, run_outcome, say, shown


def add_parsers(sub) -> None:
    p = sub.add_parser("simulate", help="simulate TLS scans of a synthetic forest plot with known poses")
    p.add_argument("preset", help="planted_conifer, mixed_temperate, rainforest, sloped or open_field")
    p.add_argument(
        "--out", required=True, help="output folder (scan_XX.laz + truth.json); replaced when the run completes"
    )
    p.add_argument("--positions", help="scanner positions 'x,y;x,y;...' in metres (default '0,0;10,0')")
    p.add_argument("--tilt", action="append", metavar="INDEX:DEG", help="tilt scan INDEX by DEG degrees (repeatable)")
    p.add_argument(
        "--step", type=number("--step", positive=True), default=0.2, help="angular step in degrees (default 0.2)"
    )
    p.add_argument(
        "--size", type=number("--size", positive=True), default=60.0, help="plot side in metres (default 60)"
    )
    p.add_argument("--seed", type=number("--seed", minimum=0, integer=True), default=0, help="random seed (default 0)")
    p.set_defaults(func=cmd_simulate, long_running=True)

    p = sub.add_parser(
        "demo",
        help="simulated data through both systems (TLS pair; ground/UAV co-registration, fusion, trees), checked against the truth",
    )
    p.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    p.add_argument("--preset", default="mixed_temperate", help="System A scene preset (default mixed_temperate)")
    p.add_argument(
        "--step",
        type=number("--step", positive=True),
        default=0.15,
        help="angular step of the simulated scans, degrees",
    )
    p.add_argument("--seed", type=number("--seed", minimum=0, integer=True), default=1, help="random seed (default 1)")
    p.add_argument(
        "--system",
        choices=("a", "b", "both"),
        default="both",
        help="System A (TLS pair), B (ground/UAV, trees) or both",
    )
    p.set_defaults(func=cmd_demo, long_running=True)

    p = sub.add_parser(
        "gui",
        help="the desktop GUI (--offscreen --project P --run --screenshot OUT.png for headless use)",
        add_help=False,
    )
    p.add_argument("gui_args", nargs=argparse.REMAINDER, help="options of the GUI (see 'forestreg gui --help')")
    p.set_defaults(func=cmd_gui, long_running=False)

    p = sub.add_parser(
        "params",
        help="print every parameter of the product (or a TOML template: sections [registration], [coregistration], [fusion], [trees])",
    )
    p.add_argument(
        "--toml", action="store_true", help="print a TOML file of the values (the defaults, or those of --params)"
    )
    p.add_argument("--params", help="a TOML parameter file to show merged over the defaults")
    p.set_defaults(func=cmd_params, long_running=False)


def cmd_simulate(args: argparse.Namespace) -> int:
    from ..app.simulation import simulate_scans
    from ..engine.core.errors import UsageError

    positions = (
        [tuple(floats(p, 2, "--positions")) for p in args.positions.split(";")]
        if args.positions
        else [(0.0, 0.0), (10.0, 0.0)]
    )
    tilted = {}
    for item in args.tilt or []:
        index, _, deg = item.partition(":")
        try:
            k, d = int(index), float(deg or 30.0)
        except ValueError as exc:
            raise UsageError(f"--tilt {item}: expected INDEX:DEG, e.g. 1:30") from exc
        if not 0 <= k < len(positions) or not math.isfinite(d):
            raise UsageError(f"--tilt {item}: scan index must be 0..{len(positions) - 1} and the angle finite")
        tilted[k] = d
    run = run_outcome(
        args.reporter,
        simulate_scans,
        args.preset,
        positions,
        args.out,
        seed=args.seed,
        step_deg=args.step,
        tilted=tilted,
        size_m=args.size,
    )
    for name, count in run.scans:
        print(f"{name}: {count} points")
    args.reporter.done("", run.result_file)
    say(f"wrote {len(run.scans)} scans and truth.json to {shown(run.out)}", args)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """System A: a simulated TLS pair registered from trunk shadows; System B: a simulated plot seen
    from the ground and from a UAV, co-registered, fused and measured. Both against the truth."""
    from ..engine.core.atomic import check_output_folder

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        check_output_folder(out, "demo")  # refuses a file with one line
    codes = []
    if args.system in ("a", "both"):
        codes.append(_demo_system_a(out, args))
    if args.system in ("b", "both"):
        codes.append(_demo_system_b(out / "system_b", args))
    return max(codes)


def _sub_reporter(args: argparse.Namespace, command: str) -> Reporter:
    mode = args.reporter.mode
    return Reporter(mode, command)


def _demo_system_a(out: Path, args: argparse.Namespace) -> int:
    """Simulate a mixed forest pair 12 m apart, register it, and compare with the truth."""
    from ..app.pair import register_pair
    from ..app.simulation import errors_against, simulated_pair
    from .register import print_register

    data = out / "scans"
    print(f"System A: simulating a '{args.preset}' plot with two scans 12 m apart in {data} ...")
    case = simulated_pair(data, args.preset, seed=args.seed, step_deg=args.step)
    reporter = _sub_reporter(args, "register")
    outcome = run_outcome(reporter, register_pair, case.reference, case.moving, out / "registration")
    code = print_register(outcome, reporter)
    if outcome.matrix is not None:
        rot, trans = errors_against(outcome.matrix, case.truth)
        print(f"against the simulator's truth: rotation error {rot:.4f} deg, translation error {100 * trans:.2f} cm")
    args.reporter.done("", out / "registration" / "result.json")
    return code


def _demo_system_b(out: Path, args: argparse.Namespace) -> int:
    """A 28 m plot: merged TLS scans (ground-based, own frame, turned 120 deg and shifted 7 m) and
    a UAV flight at 86 m; co-register, fuse, measure the trees ground-only and fused, and
    evaluate both against the simulator's trees (the 'field data')."""
    from ..app.coregistration import coregister_clouds
    from ..app.simulation import errors_against, simulated_coregistration
    from .coreg import print_coregister, run_fuse
    from .trees import run_evaluate, run_trees

    data = out / "data"
    print(f"System B: simulating a plot seen by TLS and by a UAV in {data} ...")
    case = simulated_coregistration(data, seed=args.seed)
    reporter = _sub_reporter(args, "coregister")
    outcome = run_outcome(reporter, coregister_clouds, case.ground, case.uav, out / "coregistration")
    code = print_coregister(outcome, reporter)
    if code != 0:
        return code
    rot, trans = errors_against(outcome.matrix, case.truth)
    print(f"against the simulator's truth: rotation error {rot:.4f} deg, translation error {100 * trans:.2f} cm")
    transform = out / "coregistration" / "transform.txt"
    run_fuse(case.ground, case.uav, out / "fused.laz", transform=transform, reporter=_sub_reporter(args, "fuse"))
    run_trees(case.ground, out / "trees_ground", transform=transform, reporter=_sub_reporter(args, "trees"))
    run_trees(out / "fused.laz", out / "trees_fused", reporter=_sub_reporter(args, "trees"))
    code = run_evaluate(
        [("ground", out / "trees_ground" / "trees.csv"), ("fused", out / "trees_fused" / "trees.csv")],
        case.field,
        out / "evaluation",
    )
    print(
        f"reports: {shown(out) / 'coregistration' / 'report.html'}, {shown(out) / 'trees_fused' / 'report.html'}, "
        f"{shown(out) / 'evaluation' / 'report.html'}"
    )
    args.reporter.done("", out / "evaluation" / "evaluation.json")
    return code


def check_gui_args(gui_args) -> None:
    """The GUI's options that can be checked without Qt: --size, --project, --timeout, --screenshot
    (bad input: one line, exit 2, before a window opens)."""
    from ..engine.core.atomic import check_output_file
    from ..engine.core.errors import UsageError

    values: dict[str, str] = {}
    items = list(gui_args)
    for k, item in enumerate(items):
        name, eq, value = item.partition("=")
        if name in ("--size", "--project", "--timeout", "--screenshot"):
            if not eq:
                if k + 1 >= len(items):
                    raise UsageError(f"gui {name}: a value is missing")
                value = items[k + 1]
            values[name] = value
    if "--size" in values:
        try:
            w, h = (int(v) for v in values["--size"].lower().split("x"))
        except ValueError:
            raise UsageError(
                f"gui --size must be WIDTHxHEIGHT in pixels, e.g. 1600x1000 (got {values['--size']!r})"
            ) from None
        if w <= 0 or h <= 0 or w > 20000 or h > 20000:
            raise UsageError(f"gui --size {values['--size']}: width and height must be between 1 and 20000 pixels")
    if "--timeout" in values:
        number("gui --timeout", positive=True)(values["--timeout"])
    if "--project" in values and not Path(values["--project"]).is_file():
        raise UsageError(f"gui --project {values['--project']}: no such project file")
    if "--screenshot" in values:
        check_output_file(values["--screenshot"], suffixes=(".png",))


def cmd_gui(args: argparse.Namespace) -> int:
    check_gui_args(args.gui_args)
    try:
        from ..ui.app import main as gui_main
    except ImportError as exc:
        print(
            f"forestreg: error: the GUI needs the 'gui' extras (pip install 'forestreg[gui]'): {exc}", file=sys.stderr
        )
        return 2
    return gui_main(list(args.gui_args))


def cmd_params(args: argparse.Namespace) -> int:
    from ..engine.params import ProductParams, load_params, params_toml

    params = load_params(args.params) if getattr(args, "params", None) else ProductParams()
    if args.toml:
        print(params_toml(params))
        return 0
    for r in type(params).table():
        value = params
        for part in r["name"].split("."):
            value = getattr(value, part)
        unit = r["unit"] or ""
        paper = f"  (paper: {r['paper']})" if r["paper"] else ""
        print(f"{r['name']:44} {str(value):22} {unit:7} {r['help']}{paper}")
    return 0
