"""``forestreg plot`` (and ``plot --watch``), ``plan``, ``project``, ``compare`` and ``targets``: whole plots of TLS scans (System A)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Callable, Optional

from .common import (
    PARAMS_HELP,
    add_crs_option,
    file_section,
    number,
    offsets,
    params_from_args,
    run_outcome,
    say,
    shown,
)


def _add_plot_options(p: argparse.ArgumentParser) -> None:
    """The options of a plot's project: a saved project file holds them (``project create`` takes
    them), except the survey's (:func:`_add_survey_options`), which ``project run`` takes too."""
    p.add_argument("--centre", help="the centre (root) scan: the project frame (default: the first scan)")
    p.add_argument(
        "--tilted",
        action="append",
        metavar="SCAN[:PARTNER],...",
        help="tilted scans, each optionally with the level scan at the same spot",
    )
    p.add_argument("--targets", help="targets CSV (scan,target,x,y,z in each scan's own coordinates)")
    p.add_argument(
        "--dr", type=number("--dr", positive=True), help="VOP radius D_r in metres for every link (default: automatic)"
    )
    p.add_argument("--dc", type=number("--dc", positive=True), help="reduction radius D_c in metres (default 30)")
    p.add_argument("--dh", type=offsets, help="slice offsets dh in metres, comma-separated")
    p.add_argument("--params", help=PARAMS_HELP)
    p.add_argument(
        "--positions",
        metavar="CSV",
        help="scanner positions: CSV scan,x,y,z in each scan's file coordinates (default: the E57 pose, else found from the data)",
    )
    p.add_argument(
        "--prior-poses",
        metavar="FILE",
        help="prior poses to check links against: poses.json, JSON {scan: 4x4}, or CSV scan,x,y,z[,heading_deg] (GNSS/compass)",
    )
    _add_survey_options(p)


def _add_survey_options(p: argparse.ArgumentParser) -> None:
    """``--pairs`` and ``--fixed``: how a plot's scans are registered (``plot``, ``project run``)."""
    p.add_argument(
        "--pairs",
        metavar="all|within:D|centre",
        help="register every pair (or those whose scanners stand within D m), solve a pose graph weighted by each pair's evidence, drop inconsistent links, state each pose's uncertainty",
    )
    p.add_argument(
        "--fixed", action="append", metavar="SCAN,...", help="scans held at their prior poses (with --pairs)"
    )


def _add_point_outputs(p: argparse.ArgumentParser) -> None:
    """``--merged`` and ``--e57-out``: the registered scans written as one file (``plot``, ``project run``)."""
    p.add_argument(
        "--merged",
        help="also write all registered scans into one point file (.laz/.las, or .copc.laz for a COPC file viewers such as QGIS and potree stream) with a scan_id per point (never an input)",
    )
    p.add_argument("--e57-out", help="also write the registered scans with their poses into one E57 file")


def _add_project_run_options(q: argparse.ArgumentParser) -> None:
    """The options ``project run`` takes beside the project file, ``--out`` and ``--rerun``."""
    _add_survey_options(q)
    _add_point_outputs(q)


def _add_plot_arguments(p: argparse.ArgumentParser) -> None:
    """Every argument of ``plot`` (the global flags aside)."""
    p.add_argument(
        "scans", nargs="*", metavar="SCAN", help="scan files, or one multi-scan E57 file (none with --watch)"
    )
    p.add_argument(
        "--out", required=True, help="output folder: project.json, poses.json, <scan>.transform.txt, report.html"
    )
    _add_plot_options(p)
    p.add_argument(
        "--watch",
        metavar="FOLDER",
        help="watch FOLDER (a scanner's export) and register each scan as it arrives, "
        "updating the output folder after each (with watch.json); runs until Ctrl-C or --until-scans",
    )
    p.add_argument(
        "--until-scans",
        type=number("--until-scans", minimum=1, integer=True),
        metavar="N",
        help="with --watch: end once N scans are taken in (placed or set aside; duplicates and files that are no scan do not count)",
    )
    p.add_argument(
        "--poll",
        type=number("--poll", positive=True),
        default=1.0,
        metavar="S",
        help="with --watch: seconds between two looks at the folder (default 1; a file counts once it did not change between two looks)",
    )
    _add_point_outputs(p)
    p.add_argument(
        "--registered-dir",
        help="also write each registered scan, in the centre scan's coordinates, as its own LAZ into this folder",
    )
    p.add_argument(
        "--loops",
        type=number("--loops", positive=True),
        metavar="M",
        help="also link registered scans standing within M metres of each other, and adjust all poses globally",
    )
    add_crs_option(
        p,
        "poses.json, layers.gpkg and the merged and registered clouds are in the centre scan's frame and take its CRS",
    )


def _defaults(add: Callable[[argparse.ArgumentParser], None], *given: str) -> dict[str, Any]:
    """The destinations of the arguments ``add`` declares, with their defaults (``given``: the
    required ones)."""
    p = argparse.ArgumentParser(add_help=False)
    add(p)
    return vars(p.parse_args(list(given)))


def project_run_args(plot: argparse.Namespace, project_file: Path) -> Optional[list[str]]:
    """The ``project run`` arguments that finish the ``plot`` command ``plot`` (its arguments as
    parsed) from its saved project file: the options the project holds (:func:`_add_plot_options`)
    are left out, those ``project run`` takes (:func:`_add_project_run_options`) are passed on as
    given; None when the command sets another one (e.g. ``--registered-dir``: only ``plot`` writes
    it), so the plot starts over. Handed to the batch with the parsed arguments (it does not
    import the command line, which starts it)."""
    taken = _defaults(_add_project_run_options)
    held = set(_defaults(_add_plot_options)) - set(taken)
    args = ["project", "run", str(project_file), "--out", str(plot.out)]
    for dest, default in _defaults(_add_plot_arguments, "--out", "-").items():
        value = getattr(plot, dest, default)
        if dest in ("scans", "out", *held) or value == default:
            continue
        if dest not in taken:
            return None
        flag = "--" + dest.replace("_", "-")
        for v in value if isinstance(value, list) else [value]:
            args += [flag] if v is True else [flag, str(v)]
    return args


def add_parsers(sub, add_global_flags) -> None:
    p = sub.add_parser(
        "plot", help="register all scans of a plot (each to the centre scan, tilted ones to their level partner)"
    )
    _add_plot_arguments(p)
    p.set_defaults(func=cmd_plot, long_running=True, project_run_args=project_run_args)

    p = sub.add_parser(
        "compare", help="register a plot automatically and from targets, and compare (the paper's tables 4 and 5)"
    )
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files, or one multi-scan E57 file")
    p.add_argument(
        "--out", required=True, help="output folder: comparison.json/.csv, report.html, project.json, poses.json"
    )
    _add_plot_options(p)
    p.set_defaults(func=cmd_compare, long_running=True)

    p = sub.add_parser(
        "targets", help="detect reflector targets (bright small discs/cylinders) in scans with intensity"
    )
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files with intensity")
    p.add_argument("--out", required=True, help="targets CSV to write (scan,target,x,y,z; never an input)")
    p.add_argument("--known", help="approximate targets CSV: name detections after the nearest known target")
    p.add_argument(
        "--max-distance",
        type=number("--max-distance", positive=True),
        default=0.3,
        help="largest distance to a known target, metres (default 0.3)",
    )
    p.set_defaults(func=cmd_targets, long_running=True)

    p = sub.add_parser(
        "plan",
        help="where to scan next: stems and ground not seen yet, link strength, and 1-3 scanner positions that link and see the most new stem area (plan.json, plan.gpkg)",
    )
    p.add_argument(
        "project", metavar="PROJECT_OR_OUT", help="a plot folder (of 'plot' or 'plot --watch') or a project file"
    )
    p.add_argument(
        "--n",
        type=number("--n", minimum=1, integer=True),
        default=1,
        metavar="N",
        help="how many next scans to suggest, 1 to 3 (default 1)",
    )
    p.add_argument(
        "--radius",
        type=number("--radius", positive=True),
        metavar="M",
        help="plot radius in metres around the centre scan's scanner (default: from the ground the scans saw)",
    )
    p.add_argument("--out", help="the plan file to write (.json; default plan.json beside the project file)")
    p.add_argument("--params", help=PARAMS_HELP)
    p.set_defaults(func=cmd_plan, long_running=True)

    p = sub.add_parser("project", help="create, inspect, link and re-run a saved plot project")
    psub = p.add_subparsers(dest="action", required=True, metavar="{create,show,link,run}")
    q = psub.add_parser("create", help="create a project file from scans")
    q.add_argument("project", help="project file to write (.json; never a scan)")
    q.add_argument("scans", nargs="+", metavar="SCAN", help="scan files")
    _add_plot_options(q)
    add_global_flags(q)
    q.set_defaults(func=cmd_project, out=None, long_running=False)
    q = psub.add_parser("show", help="print the scans, links and results of a project")
    q.add_argument("project", help="project file (.json)")
    add_global_flags(q)
    q.set_defaults(func=cmd_project, long_running=False)
    q = psub.add_parser("link", help="link MOVING to REFERENCE (replacing its link, or --extra for a loop)")
    q.add_argument("project", help="project file (.json)")
    q.add_argument("moving", help="name of the scan to place")
    q.add_argument("reference", help="name of the scan it is registered onto")
    q.add_argument("--dr", type=number("--dr", positive=True), help="VOP radius for this link, m")
    q.add_argument("--extra", action="store_true", help="add an extra link (closes a loop for the global adjustment)")
    add_global_flags(q)
    q.set_defaults(func=cmd_project, long_running=False)
    q = psub.add_parser("run", help="register the project's scans (links that succeeded are kept unless --rerun)")
    q.add_argument("project", help="project file (.json)")
    q.add_argument(
        "--out",
        help="output folder (default: the project's folder when forestreg made it, else <project>_results beside the project file)",
    )
    q.add_argument("--rerun", action="store_true", help="run every link again")
    _add_project_run_options(q)
    add_global_flags(q)
    q.set_defaults(func=cmd_project, long_running=True)


# ----------------------------------------------------------------------------- runs


def project_from_args(args: argparse.Namespace):
    """A new project from the scans, centre, tilted marks, targets and parameters on the command line."""
    from ..app.plot import new_project

    return new_project(
        args.scans,
        params_from_args(args),
        name=Path(args.out).name if getattr(args, "out", None) else "plot",
        centre=args.centre,
        tilted=args.tilted or [],
        targets=getattr(args, "targets", None),
        positions=getattr(args, "positions", None),
        prior_poses=getattr(args, "prior_poses", None),
        fixed=getattr(args, "fixed", None) or [],
        scanner_params=file_section(args, "scanner_position"),
    )


def check_survey_options(args: argparse.Namespace) -> None:
    """Bad --pairs / --positions / --prior-poses: one line and exit 2, before any work."""
    from ..app.survey import check_survey_options as check

    check(getattr(args, "pairs", None), getattr(args, "positions", None), getattr(args, "prior_poses", None))


def _extra_outputs(args: argparse.Namespace) -> dict:
    return {name: getattr(args, name, None) for name in ("merged", "registered_dir", "e57_out")}


def run_project(project, out: Path, args: argparse.Namespace) -> int:
    """Register the project into ``out`` (:func:`forestreg.app.plot.run_plot`) and print the outcome."""
    from ..app.plot import run_plot

    run = run_outcome(
        args.reporter,
        run_plot,
        project,
        out,
        pairs=getattr(args, "pairs", None),
        fixed=getattr(args, "fixed", None) or [],
        rerun=getattr(args, "rerun", False),
        loops=getattr(args, "loops", None),
        survey=file_section(args, "survey"),
        crs=getattr(args, "crs", None),
        **_extra_outputs(args),
    )
    return print_plot_run(run, args)


def print_plot_run(run, args: argparse.Namespace) -> int:
    """The lines of a finished plot run (:class:`forestreg.app.plot.PlotRun`); the exit code."""
    reporter, project, out = args.reporter, run.project, run.out
    outcome = run.result
    for what, (path, count) in run.written.items():
        if what == "merged":
            print(f"merged {count} points into {args.merged}")
        elif what == "registered_dir":
            print(f"wrote {count} registered scans to {args.registered_dir}")
        else:
            print(f"wrote {count} registered scans with their poses to {args.e57_out}")
    sigma = run.uncertainty
    for name, status in outcome.scans.items():
        extra = f" - {outcome.reasons[name]}" if name in outcome.reasons else ""
        link = project.link_of(name)
        onto = f" onto {link.reference}" if link is not None and status == "ok" else ""
        u = sigma.get(name) if status == "ok" else None
        if u is not None and u.known:
            onto += f" (1 sigma {100 * u.translation_m:.1f} cm, {u.rotation_deg:.3f} deg)"
        print(f"{name}: {status}{onto}{extra}")
    for d in run.dropped:
        print(f"dropped link {d.moving} -> {d.reference}: {d.reason}")
    if run.residual is not None:
        links, worst = run.residual
        print(f"global adjustment over {links} links: largest link residual {100 * worst:.1f} cm")
    if (out / "report.html").exists():
        print(f"report: {shown(out) / 'report.html'}")
    reporter.done("", run.result_file)
    n_ok = len(outcome.registered)
    summary = f"{n_ok} of {len(outcome.scans)} scans registered -> {shown(out) / 'poses.json'}"
    say(f"poses: {shown(out) / 'poses.json'}" if not outcome.failed else summary, args, err=bool(outcome.failed))
    return 0 if run else 1


def cmd_plot(args: argparse.Namespace) -> int:
    """``plot``: the whole use case is :func:`forestreg.app.plot.plot_scans` (its checks first)."""
    from ..app.plot import plot_scans
    from ..engine.core.errors import UsageError

    if getattr(args, "watch", None):
        return cmd_watch(args)
    if not args.scans:
        raise UsageError("plot needs scan files (SCAN ...), or --watch FOLDER")
    if getattr(args, "until_scans", None) is not None:
        raise UsageError("--until-scans goes with --watch FOLDER")

    def resumed(out: Path, kept: int, links: int) -> None:
        say(
            f"resuming the stopped run in {shown(out)}: {kept} of {links} links registered before are kept",
            args,
            err=True,
        )

    def interrupted() -> str:
        # a plot run keeps what it has linked (OUT/project.json) so that the same command resumes it
        if not (Path(args.out) / "project.json").is_file():
            return ""
        return (
            f"interrupted: the links registered so far are kept in {shown(Path(args.out))} (project.json); "
            "the same command resumes from them"
        )

    args.interrupted_message = interrupted
    run = run_outcome(
        args.reporter,
        plot_scans,
        args.scans,
        args.out,
        params_from_args(args),
        centre=args.centre,
        tilted=args.tilted or [],
        targets=getattr(args, "targets", None),
        positions=getattr(args, "positions", None),
        prior_poses=getattr(args, "prior_poses", None),
        fixed=getattr(args, "fixed", None) or [],
        scanner_params=file_section(args, "scanner_position"),
        pairs=getattr(args, "pairs", None),
        loops=getattr(args, "loops", None),
        survey=file_section(args, "survey"),
        crs=getattr(args, "crs", None),
        on_resume=resumed,
        **_extra_outputs(args),
    )
    return print_plot_run(run, args)


#: Options of ``plot`` a watch does not take (each scan is registered onto the centre scan, or the
#: placed scans nearest it, as it arrives)
_NOT_WITH_WATCH = (
    "tilted",
    "targets",
    "pairs",
    "positions",
    "prior_poses",
    "fixed",
    "merged",
    "e57_out",
    "registered_dir",
    "loops",
)


def cmd_watch(args: argparse.Namespace) -> int:
    """``plot --watch FOLDER``: register each scan arriving in FOLDER (:func:`forestreg.app.watch.watch_plot`),
    one line per scan (one JSON event per scan with ``--progress jsonl``); Ctrl-C ends it (exit 0)."""
    import json
    import sys

    from ..app.watch import watch_plot
    from ..engine.core.errors import UsageError

    if args.scans:
        raise UsageError(f"--watch takes the scans from {args.watch}: give no scan files ({args.scans[0]} ...)")
    given = [f"--{name.replace('_', '-')}" for name in _NOT_WITH_WATCH if getattr(args, name, None)]
    if given:
        raise UsageError(
            f"{', '.join(given)}: not with --watch (each scan is registered onto the centre scan as it arrives; "
            "run 'forestreg plot' on the scans afterwards for these)"
        )
    jsonl = args.reporter.mode == "jsonl"

    def show(event) -> None:
        if jsonl:
            sys.stderr.write(json.dumps(event.to_dict()) + "\n")
            sys.stderr.flush()
        print(event.message, flush=True)

    def started(resumed: int) -> None:
        before = f", going on from the {resumed} scans placed before" if resumed else ""
        say(f"watching {args.watch} -> {shown(args.out)}{before} (Ctrl-C to stop)", args, err=True)

    run = run_outcome(
        args.reporter,
        watch_plot,
        args.watch,
        args.out,
        params_from_args(args),
        centre=args.centre,
        scanner_params=file_section(args, "scanner_position"),
        plan_params=file_section(args, "plan"),
        poll_s=args.poll,
        until_scans=args.until_scans,
        on_event=show,
        on_start=started,
        progress=None if args.reporter.mode == "none" else args.reporter,
    )
    out = Path(args.out)
    summary = f"{len(run.placed)} of {len(run.taken)} scans placed -> {shown(out) / 'poses.json'}"
    if run.stopped:
        summary = f"stopped: {summary}; the same command goes on from here"
    args.reporter.done(summary, out / "poses.json")
    say(summary, args, err=bool(run.aside) and not run.stopped)
    return 0 if run.stopped or run else 1


def cmd_plan(args: argparse.Namespace) -> int:
    """``plan``: the next scans of a plot (:func:`forestreg.app.plan.plan_next`) and a short table."""
    from ..app.plan import plan_next
    from ..engine.core.errors import UsageError

    if args.n > 3:
        raise UsageError(f"--n must be 1, 2 or 3, got {args.n}")
    params = file_section(args, "plan")
    if args.radius is not None:
        from ..engine.tls.params import PlanParams

        params = (params or PlanParams()).replace(radius_m=args.radius)
    run = run_outcome(args.reporter, plan_next, args.project, n=args.n, params=params, out=args.out)
    plan = run.plan
    print(
        f"plot: {len(plan.scanners)} scans placed, radius {plan.radius_m:.1f} m around ({plan.centre[0]:.1f}, {plan.centre[1]:.1f}) "
        f"in {run.frame}'s coordinates"
    )
    print(
        f"stems: {plan.stems} mapped, {plan.stems_seen_twice} seen by two or more scans; stem area seen {plan.stem_area_seen_m2:.1f} m2, "
        f"not seen {plan.stem_area_unseen_m2:.1f} m2; ground seen {plan.ground_seen_m2:.0f} m2, not seen {plan.ground_unseen_m2:.0f} m2"
    )
    for link in run.links:
        matched = "-" if link.matched is None else link.matched
        sigma = (
            ""
            if link.translation_m is None or link.rotation_deg is None
            else f", 1 sigma {100 * link.translation_m:.1f} cm / {link.rotation_deg:.3f} deg"
        )
        print(f"link {link.moving} -> {link.reference}: {link.strength} ({matched} trunk shadows{sigma})")
    if plan.suggestions:
        print(
            f"{'next':>4} {'x (m)':>8} {'y (m)':>8}  {'links to':<20} {'shared':>6} {'new stem m2':>11} {'new view m2':>11}"
        )
        for k, s in enumerate(plan.suggestions, 1):
            print(
                f"{k:>4} {s.x:>8.1f} {s.y:>8.1f}  {s.links_to:<20} {s.shared_stems:>6} {s.new_stem_area_m2:>11.1f} {s.new_view_m2:>11.0f}"
            )
    args.reporter.done("", run.out)
    if not run:
        say(f"no next scan: {run.reason} -> {shown(run.out)}", args, err=True)
        return 1
    say(f"plan: {shown(run.out)}" + (f" and {shown(run.layers)} (the next_scans layer)" if run.layers else ""), args)
    return 0


def cmd_project(args: argparse.Namespace) -> int:
    from ..app.plot import check_extra_outputs, check_scan_files, link_summary, load_project, plot_folder
    from ..engine.core.errors import OutputPathError, UsageError

    if args.action == "create":
        target = Path(args.project)
        if target.suffix.lower() != ".json":
            raise OutputPathError(
                f"the project file {target} must end in .json (did you forget it? usage: project create P.json SCAN ...)"
            )
        if target.exists():
            raise OutputPathError(f"{target} exists already: give a new project file")
        from ..engine.core.atomic import check_output_file

        check_output_file(target, inputs=args.scans, suffixes=(".json",))
        check_survey_options(args)
        check_scan_files(args.scans)
        project = project_from_args(args)
        path = project.save(target)
        say(f"created {path} with {len(project.scans)} scans, centre {project.centre}", args)
        return 0
    project = load_project(args.project)
    if args.action == "show":
        poses = project.poses()
        print(f"project {project.name}: {len(project.scans)} scans, centre {project.centre}")
        for s in project.scans:
            run = link_summary(project.link_of(s.name))
            state = "centre" if s.name == project.centre else ("not run" if run is None else run.status)
            details = ""
            if run is not None:
                details = f" onto {run.reference}, {'-' if run.matched is None else run.matched} matched VOPs"
                if run.icp_std_m is not None:
                    details += f", ICP std {1000 * run.icp_std_m:.1f} mm"
                if run.reason:
                    details += f" ({run.reason})"
            t = " [tilted]" if s.tilted else ""
            placed = (
                ""
                if poses.get(s.name) is None
                else f" at ({poses[s.name][0, 3]:.2f}, {poses[s.name][1, 3]:.2f}, {poses[s.name][2, 3]:.2f})"
            )
            print(f"  {s.name}{t}: {state}{details}{placed}")
        return 0
    if args.action == "link":
        for name in (args.moving, args.reference):
            if not project.has_scan(name):
                raise UsageError(
                    f"{name}: no such scan in the project (scans: {', '.join(s.name for s in project.scans)})"
                )
        if args.extra:  # the project's rules (no link to itself, the centre not moved) are the project's own
            project.add_link(args.moving, args.reference, vop_radius_m=args.dr)
        else:
            project.set_link(args.moving, args.reference, vop_radius_m=args.dr)
        project.save()
        say(f"linked {args.moving} -> {args.reference}{' (extra link)' if args.extra else ''}", args)
        return 0
    inputs = [s.path for s in project.scans]
    check_survey_options(args)
    check_extra_outputs(inputs, out=args.out, **_extra_outputs(args))
    if args.out:
        out = plot_folder(args.out, inputs)
    else:
        out = _default_project_out(project, inputs)
    return run_project(project, out, args)


def _default_project_out(project, inputs) -> Path:
    """Where ``project run`` without ``--out`` writes: the project's folder when it is an output
    folder of forestreg (a plot's, holding its project.json), else ``<project>_results`` beside
    the project file; never over a user's own files (a report.html or poses.json of theirs)."""
    from ..app.plot import plot_folder
    from ..engine.core.atomic import MARKER

    folder = project.path.parent
    if (folder / MARKER).is_file():
        return plot_folder(folder, inputs)
    out = folder / f"{project.path.stem}_results"
    return plot_folder(out, inputs)


def cmd_compare(args: argparse.Namespace) -> int:
    from ..app.comparison import compare_plot
    from ..app.plot import check_scan_files_exist
    from ..engine.core.atomic import check_output_folder

    check_scan_files_exist(args.scans)
    inputs = args.scans + ([args.targets] if args.targets else [])
    out = check_output_folder(args.out, "compare", inputs=inputs)
    project = project_from_args(args)
    run = run_outcome(args.reporter, compare_plot, project, out, inputs=inputs)
    json_path = run.json_path
    print(f"{'pair':32} {'auto std':>9} {'VOPs':>5} {'manual std':>11} {'targets':>7} {'rot diff':>9} {'shift':>8}")

    def cell(side):
        if not side.ok:
            return "failed"
        return "n/a" if side.icp_std_m is None else f"{100 * side.icp_std_m:.2f} cm"

    for p in run.pairs:
        rot = "-" if p.rotation_difference_deg is None else f"{p.rotation_difference_deg:.3f} deg"
        shift = "-" if p.translation_difference_m is None else f"{100 * p.translation_difference_m:.1f} cm"
        matched = p.auto.matched if p.auto.matched is not None else "-"
        targets = p.manual.targets if p.manual.targets is not None else "-"
        print(
            f"{p.moving + ' -> ' + p.reference:32} {cell(p.auto):>9} {str(matched):>5} "
            f"{cell(p.manual):>11} {str(targets):>7} {rot:>9} {shift:>8}"
        )
    for line in run.failed:
        print(f"  failed: {line}")
    fmt = lambda v: "n/a" if v is None else f"{100 * v:.2f} cm"  # noqa: E731
    print(
        f"average target distance residual: auto {fmt(run.auto_target_residual_m)}, manual {fmt(run.manual_target_residual_m)}"
        + ("" if not run.target_residual_note else f" ({run.target_residual_note})")
    )
    if run.report is not None:
        print(f"report: {shown(out) / 'report.html'}")
    args.reporter.done("", json_path)
    failed = run.failed
    say(
        f"comparison: {json_path}" if not failed else f"{len(failed)} registrations failed -> {json_path}",
        args,
        err=bool(failed),
    )
    return 0 if run else 1


def cmd_targets(args: argparse.Namespace) -> int:
    from ..app.targets import detect_targets

    run = run_outcome(
        args.reporter, detect_targets, args.scans, args.out, known=args.known, max_distance=args.max_distance
    )
    for t in run.scans:
        print(
            f"{t.name}: {t.detected} reflectors detected"
            + (f", {t.named} named after known targets" if t.named is not None else "")
        )
    args.reporter.done("", args.out)
    say(f"targets: {args.out} (check them, rename to shared ids across scans, then use --targets)", args)
    return 0
