"""``forestreg plot``, ``project``, ``compare`` and ``targets``: whole plots of TLS scans (System A)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .common import PARAMS_HELP, check_replaceable_point_file, log, number, offsets, params_from_args, say, shown

POINT_SUFFIXES = (".laz", ".las", ".ply", ".xyz", ".txt")


def _add_plot_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--centre", help="the centre (root) scan: the project frame (default: the first scan)")
    p.add_argument("--tilted", action="append", metavar="SCAN[:PARTNER],...", help="tilted scans, each optionally with the level scan at the same spot")
    p.add_argument("--targets", help="targets CSV (scan,target,x,y,z in each scan's own coordinates)")
    p.add_argument("--dr", type=number("--dr", positive=True), help="VOP radius D_r in metres for every link (default: automatic)")
    p.add_argument("--dc", type=number("--dc", positive=True), help="reduction radius D_c in metres (default 30)")
    p.add_argument("--dh", type=offsets, help="slice offsets dh in metres, comma-separated")
    p.add_argument("--params", help=PARAMS_HELP)
    p.add_argument("--pairs", metavar="all|within:D|centre", help="register every pair (or those whose scanners stand within D m), solve a pose graph weighted by each pair's evidence, drop inconsistent links, state each pose's uncertainty")
    p.add_argument("--positions", metavar="CSV", help="scanner positions: CSV scan,x,y,z in each scan's file coordinates (default: the E57 pose, else found from the data)")
    p.add_argument("--prior-poses", metavar="FILE", help="prior poses to check links against: poses.json, JSON {scan: 4x4}, or CSV scan,x,y,z[,heading_deg] (GNSS/compass)")
    p.add_argument("--fixed", action="append", metavar="SCAN,...", help="scans held at their prior poses (with --pairs)")


def add_parsers(sub, add_global_flags) -> None:
    p = sub.add_parser("plot", help="register all scans of a plot (each to the centre scan, tilted ones to their level partner)")
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files, or one multi-scan E57 file")
    p.add_argument("--out", required=True, help="output folder: project.json, poses.json, <scan>.transform.txt, report.html")
    _add_plot_options(p)
    p.add_argument("--merged", help="also write all registered scans into one point file (.laz/.las, or .copc.laz for a COPC file viewers such as QGIS and potree stream) with a scan_id per point (never an input)")
    p.add_argument("--e57-out", help="also write the registered scans with their poses into one E57 file")
    p.add_argument("--registered-dir", help="also write each registered scan, in the centre scan's coordinates, as its own LAZ into this folder")
    p.add_argument("--loops", type=number("--loops", positive=True), metavar="M", help="also link registered scans standing within M metres of each other, and adjust all poses globally")
    p.set_defaults(func=cmd_plot, long_running=True)

    p = sub.add_parser("compare", help="register a plot automatically and from targets, and compare (the paper's tables 4 and 5)")
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files, or one multi-scan E57 file")
    p.add_argument("--out", required=True, help="output folder: comparison.json/.csv, report.html, project.json, poses.json")
    _add_plot_options(p)
    p.set_defaults(func=cmd_compare, long_running=True)

    p = sub.add_parser("targets", help="detect reflector targets (bright small discs/cylinders) in scans with intensity")
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files with intensity")
    p.add_argument("--out", required=True, help="targets CSV to write (scan,target,x,y,z; never an input)")
    p.add_argument("--known", help="approximate targets CSV: name detections after the nearest known target")
    p.add_argument("--max-distance", type=number("--max-distance", positive=True), default=0.3, help="largest distance to a known target, metres (default 0.3)")
    p.set_defaults(func=cmd_targets, long_running=True)

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
    q.add_argument("--out", help="output folder (default: the project's folder)")
    q.add_argument("--rerun", action="store_true", help="run every link again")
    q.add_argument("--pairs", metavar="all|within:D|centre", help="register every pair (or those within D m), pose graph, inconsistent links dropped, uncertainty per pose")
    q.add_argument("--fixed", action="append", metavar="SCAN,...", help="scans held at their prior poses (with --pairs)")
    q.add_argument("--merged", help="also write all registered scans into one point file (.laz/.las, or .copc.laz for COPC; never an input)")
    q.add_argument("--e57-out", help="also write the registered scans with their poses into one E57 file")
    add_global_flags(q)
    q.set_defaults(func=cmd_project, long_running=True)


# ----------------------------------------------------------------------------- checks


def _check_scan_files(paths) -> None:
    """Every scan can be read (missing, empty, corrupt or garbage files: one line, exit 2)."""
    from ..engine.io import read_scan

    for p in paths:
        if Path(p).suffix.lower() == ".e57":
            from ..engine.io.base import check_readable

            check_readable(p)
            continue
        read_scan(p)


def _check_extra_outputs(args, inputs) -> None:
    """--merged, --e57-out, --registered-dir: refused before the work when they would overwrite
    an input or a file of another kind."""
    from ..engine.core.atomic import check_output_file, check_output_folder

    if getattr(args, "merged", None):
        check_output_file(args.merged, inputs=inputs, suffixes=POINT_SUFFIXES)
        check_replaceable_point_file(args.merged, "scan_id", "merged cloud")
    if getattr(args, "e57_out", None):
        check_output_file(args.e57_out, inputs=inputs, suffixes=(".e57",))
    if getattr(args, "registered_dir", None):
        check_output_folder(args.registered_dir, "registered-scans", inputs=inputs)


def project_from_args(args: argparse.Namespace):
    """A new project from the scans, centre, tilted marks, targets and parameters on the command line."""
    from ..engine.core.errors import UsageError
    from ..engine.tls.project import Project

    if len(args.scans) == 1 and Path(args.scans[0]).suffix.lower() == ".e57":
        from ..engine.tls.plot import project_from_e57

        project = project_from_e57(args.scans[0])
        project.params = params_from_args(args)
    else:
        project = Project(name=Path(args.out).name if getattr(args, "out", None) else "plot", params=params_from_args(args))
        for path in args.scans:
            project.add_scan(path)
    names = {Path(p).name: s.name for p, s in zip(args.scans, project.scans)} if len(args.scans) == len(project.scans) else {}

    def known(name: str, option: str) -> str:
        resolved = names.get(Path(name).name, name)
        if not project.has_scan(resolved):
            raise UsageError(f"{option} {name}: not one of the plot's scans ({', '.join(s.name for s in project.scans)})")
        return resolved

    if args.centre:
        project.centre = known(args.centre, "--centre")
    for item in ",".join(args.tilted or []).split(","):
        if not item.strip():
            continue
        tilted, _, partner = item.partition(":")
        entry = project.scan(known(tilted, "--tilted"))
        entry.tilted = True
        if partner:
            other = known(partner, "--tilted")
            if other == entry.name:
                raise UsageError(f"--tilted {item}: a scan cannot be its own level partner")
            entry.level_partner = other
    _survey_inputs(project, args, known)
    if getattr(args, "targets", None):
        from ..engine.tls.manual import read_targets_csv

        for scan_name, targets in read_targets_csv(args.targets).items():
            if project.has_scan(scan_name):
                project.scan(scan_name).targets = targets
            else:
                log.warning("targets for %s: no such scan in the plot", scan_name)
    return project


def check_survey_options(args: argparse.Namespace) -> None:
    """Bad --pairs / --positions / --prior-poses: one line and exit 2, before any work."""
    from ..engine.tls.survey import parse_pairs, read_positions_csv, read_prior_poses

    if getattr(args, "pairs", None):
        parse_pairs(args.pairs)
    if getattr(args, "positions", None):
        read_positions_csv(args.positions)
    if getattr(args, "prior_poses", None):
        read_prior_poses(args.prior_poses)


def _survey_inputs(project, args: argparse.Namespace, known) -> None:
    """Scanner positions (--positions CSV), prior poses (--prior-poses) and --fixed names into the project."""
    from ..engine.tls.survey import read_positions_csv, read_prior_poses

    if getattr(args, "positions", None):
        for name, xyz in read_positions_csv(args.positions).items():
            project.scan(known(name, "--positions")).scanner_position = xyz
    if getattr(args, "prior_poses", None):
        for name, pose in read_prior_poses(args.prior_poses).items():
            project.scan(known(name, "--prior-poses")).prior_pose = pose
    for name in ",".join(getattr(args, "fixed", None) or []).split(","):
        if name.strip():
            known(name.strip(), "--fixed")


def _fixed_names(project, args: argparse.Namespace) -> tuple[str, ...]:
    names = {s.name: s.name for s in project.scans} | {Path(s.path).name: s.name for s in project.scans}
    return tuple(names.get(n.strip(), n.strip()) for n in ",".join(getattr(args, "fixed", None) or []).split(",") if n.strip())


def _publish(tmp: Path, out: Path, scan_names) -> None:
    """Move the finished products from ``tmp`` into ``out`` (each by one rename; poses.json last,
    so a poses.json always belongs to the transforms beside it), and drop the stale transforms of
    the project's scans (no other file)."""
    import os
    import shutil

    for name in scan_names:
        stale = out / f"{name}.transform.txt"
        if stale.is_file() and not (tmp / stale.name).exists():
            stale.unlink()
    files = sorted(tmp.iterdir(), key=lambda p: p.name == "poses.json")
    for f in files:
        target = out / f.name
        if f.is_dir():
            if target.exists():
                shutil.rmtree(target)
        os.replace(f, target)
    shutil.rmtree(tmp, ignore_errors=True)


def _writes_scans(args: argparse.Namespace) -> bool:
    """Whether the run writes registered points (merged, per scan or E57), which carry the
    scans' intensity; otherwise the scans are read without it."""
    return any(getattr(args, name, None) for name in ("merged", "registered_dir", "e57_out"))


def run_project(project, out: Path, args: argparse.Namespace, scans=None) -> int:
    """Register the project, then write poses, transforms and the report into ``out``."""
    import tempfile

    from ..engine.tls.plot import ScanCache, add_neighbour_links, adjust_poses, register_project, write_merged, write_poses
    from .common import import_in_background

    # the report's figures need matplotlib (~0.4 s of imports): loaded while the scans are
    # registered, not on the single thread that writes the report at the end
    import_in_background(".engine.report.plot_report", kernels=True)
    if scans is None:
        scans = ScanCache(project, with_intensity=_writes_scans(args))
        _check_scans_near_their_scanners(project, scans)
    reporter = args.reporter
    try:
        if getattr(args, "pairs", None):
            from ..engine.tls.survey import SurveyParams, parse_pairs, register_survey

            pairs, distance = parse_pairs(args.pairs)
            survey = SurveyParams(pairs=pairs, max_distance_m=distance, fixed=_fixed_names(project, args))
            outcome = register_survey(project, survey, rerun=getattr(args, "rerun", False), progress=reporter, scans=scans)
        else:
            outcome = register_project(project, rerun=getattr(args, "rerun", False), progress=reporter, scans=scans)
        if getattr(args, "loops", None) and not getattr(args, "pairs", None):
            added = add_neighbour_links(project, args.loops)
            if added:
                log.info("closing %d loops between neighbouring scans", len(added))
                register_project(project, progress=reporter, scans=scans)
    finally:
        reporter.close()
    adjusted = adjust_poses(project, scans) if not getattr(args, "pairs", None) else project.adjustment
    if project.path is not None:
        project.save()
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".forestreg-tmp-products.", dir=out))
    try:
        write_poses(project, tmp, outcome)
        try:
            from ..engine.report.plot_report import write_plot_report

            write_plot_report(project, tmp / "report.html", scans=scans)
        except Exception as exc:  # a report must never lose the result
            log.warning("could not write the report: %s", exc)
        _publish(tmp, out, [s.name for s in project.scans])
    except BaseException:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if getattr(args, "merged", None):
        count = write_merged(project, args.merged, scans)
        print(f"merged {count} points into {args.merged}")
    if getattr(args, "registered_dir", None):
        from ..engine.core.atomic import output_folder
        from ..engine.tls.plot import write_registered_scans

        with output_folder(args.registered_dir, "registered-scans") as rtmp:
            count = write_registered_scans(project, rtmp, scans)
        print(f"wrote {count} registered scans to {args.registered_dir}")
    if getattr(args, "e57_out", None):
        from ..engine.tls.plot import write_registered_e57

        count = write_registered_e57(project, args.e57_out, scans)
        print(f"wrote {count} registered scans with their poses to {args.e57_out}")
    from ..engine.tls.plot import pose_uncertainty

    sigma = pose_uncertainty(project)
    for name, status in outcome.status.items():
        extra = f" - {outcome.reasons[name]}" if name in outcome.reasons else ""
        link = project.link_of(name)
        onto = f" onto {link.reference}" if link is not None and status == "ok" else ""
        u = sigma.get(name) if status == "ok" else None
        if u and u.get("translation_m") is not None and u.get("rotation_deg") is not None:
            onto += f" (1 sigma {100 * u['translation_m']:.1f} cm, {u['rotation_deg']:.3f} deg)"
        print(f"{name}: {status}{onto}{extra}")
    for d in (project.adjustment or {}).get("dropped") or []:
        print(f"dropped link {d['moving']} -> {d['reference']}: {d['reason']}")
    if adjusted:
        worst = max((r["after"]["translation_m"] for r in adjusted["links"]), default=0.0)
        print(f"global adjustment over {len(adjusted['links'])} links: largest link residual {100 * worst:.1f} cm")
    if (out / "report.html").exists():
        print(f"report: {shown(out) / 'report.html'}")
    reporter.done("", out / "poses.json")
    n_ok = len(outcome.registered)
    summary = f"{n_ok} of {len(outcome.status)} scans registered -> {shown(out) / 'poses.json'}"
    say(f"poses: {shown(out) / 'poses.json'}" if not outcome.failed else summary, args, err=bool(outcome.failed))
    return 0 if not outcome.failed else 1


def _check_scans_near_their_scanners(project, scans) -> None:
    """Before the work: when no scan of the plot has points near its scanner (georeferenced scans
    without scanner positions, or files in cm/mm), refuse with one line instead of failing every
    link after minutes. A single such scan fails its own link with the reason."""
    from ..engine.core.errors import ScanDataError, ScanReadError, UsageError
    from ..engine.tls.scanner_position import ScannerPositionError
    from .register import check_near_scanner

    problems = []
    for s in project.scans:
        try:
            check_near_scanner(scans(s.name), project.params.max_range_m, s.path, "m")
        except (UsageError, ScannerPositionError) as exc:  # no scanner near the data: a unit or position problem
            problems.append(str(exc))
            continue
        except (ScanReadError, ScanDataError):
            pass  # unreadable: its link reports it
        break  # one scan without the problem: the plot goes on (reading every scan first costs minutes)
    if problems and len(problems) == len(project.scans):
        raise UsageError(problems[0])


def _plot_folder(out, scans) -> Path:
    """The plot's working folder: absent, empty or an earlier plot folder (marked)."""
    from ..engine.core.atomic import MARKER, check_output_folder

    folder = check_output_folder(out, "plot", inputs=scans)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / MARKER).write_text("plot\n", encoding="utf-8")
    return folder


def cmd_plot(args: argparse.Namespace) -> int:
    check_survey_options(args)
    _check_scan_files_exist(args.scans)
    _check_extra_outputs(args, args.scans)
    project = project_from_args(args)
    from ..engine.tls.plot import ScanCache

    scans = ScanCache(project, with_intensity=_writes_scans(args))
    _check_scans_near_their_scanners(project, scans)  # before anything is written
    out = _plot_folder(args.out, args.scans)
    project.save(out / "project.json")
    return run_project(project, out, args, scans)


def _check_scan_files_exist(paths) -> None:
    """A missing scan is a typo (exit 2, before any work); an existing but unreadable scan is
    reported as failed while the others are registered. A plot needs two scans (or one multi-scan
    E57 file), each given once."""
    from ..engine.core.errors import ScanReadError, UsageError

    if len(paths) == 1 and Path(paths[0]).suffix.lower() != ".e57":
        raise UsageError(f"a plot needs at least two scans (or one multi-scan E57 file); got only {paths[0]}")
    resolved = [Path(p).resolve() for p in paths]
    twice = sorted({str(p) for p in paths if resolved.count(Path(p).resolve()) > 1})
    if twice:
        raise UsageError(f"a scan is given twice: {', '.join(twice)}")

    for p in paths:
        if not Path(p).exists():
            raise ScanReadError(f"{p}: no such file")
        if Path(p).is_dir():
            raise ScanReadError(f"{p}: is a folder, not a scan file")


def cmd_project(args: argparse.Namespace) -> int:
    from ..engine.core.errors import OutputPathError, UsageError
    from ..engine.tls.project import Project

    if args.action == "create":
        target = Path(args.project)
        if target.suffix.lower() != ".json":
            raise OutputPathError(f"the project file {target} must end in .json (did you forget it? usage: project create P.json SCAN ...)")
        if target.exists():
            raise OutputPathError(f"{target} exists already: give a new project file")
        from ..engine.core.atomic import check_output_file

        check_output_file(target, inputs=args.scans, suffixes=(".json",))
        check_survey_options(args)
        _check_scan_files(args.scans)
        project = project_from_args(args)
        path = project.save(target)
        say(f"created {path} with {len(project.scans)} scans, centre {project.centre}", args)
        return 0
    project = Project.load(args.project)
    if args.action == "show":
        poses = project.poses()
        print(f"project {project.name}: {len(project.scans)} scans, centre {project.centre}")
        for s in project.scans:
            link = project.link_of(s.name)
            state = "centre" if s.name == project.centre else ("not run" if link is None or link.result is None else link.result.get("status"))
            details = ""
            if link is not None and link.result is not None:
                r = link.result
                details = f" onto {link.reference}, {r.get('matched', '-')} matched VOPs"
                if r.get("icp"):
                    details += f", ICP std {1000 * r['icp']['std_m']:.1f} mm"
                if r.get("reason"):
                    details += f" ({r['reason']})"
            t = " [tilted]" if s.tilted else ""
            placed = "" if poses.get(s.name) is None else f" at ({poses[s.name][0, 3]:.2f}, {poses[s.name][1, 3]:.2f}, {poses[s.name][2, 3]:.2f})"
            print(f"  {s.name}{t}: {state}{details}{placed}")
        return 0
    if args.action == "link":
        for name in (args.moving, args.reference):
            if not project.has_scan(name):
                raise UsageError(f"{name}: no such scan in the project (scans: {', '.join(s.name for s in project.scans)})")
        if args.moving == args.reference:
            raise UsageError(f"a scan cannot be linked to itself ({args.moving})")
        if args.extra:
            project.add_link(args.moving, args.reference, vop_radius_m=args.dr)
        else:
            project.set_link(args.moving, args.reference, vop_radius_m=args.dr)
        project.save()
        say(f"linked {args.moving} -> {args.reference}{' (extra link)' if args.extra else ''}", args)
        return 0
    inputs = [s.path for s in project.scans]
    check_survey_options(args)
    _check_extra_outputs(args, inputs)
    if args.out:
        out = _plot_folder(args.out, inputs)
    else:
        out = project.path.parent
    return run_project(project, out, args)


def cmd_compare(args: argparse.Namespace) -> int:
    from ..engine.core.atomic import check_output_folder, output_folder
    from ..engine.tls.compare import compare_auto_manual, write_comparison
    from ..engine.tls.plot import ScanCache, write_poses

    from ..engine.core.errors import UsageError

    _check_scan_files_exist(args.scans)
    out = check_output_folder(args.out, "compare", inputs=args.scans + ([args.targets] if args.targets else []))
    project = project_from_args(args)
    with_targets = [s.name for s in project.scans if s.targets]
    if len(with_targets) < 2:
        raise UsageError("compare needs targets in at least two scans (--targets TARGETS.csv with scan,target,x,y,z; "
                         f"scans with targets: {', '.join(with_targets) or 'none'})")
    scans = ScanCache(project)
    try:
        comparison = compare_auto_manual(project, scans=scans, progress=args.reporter)
    finally:
        args.reporter.close()
    with output_folder(out, "compare") as tmp:
        project.save(tmp / "project.json")
        write_poses(project, tmp)
        json_path, _ = write_comparison(comparison, tmp)
        try:
            from ..engine.report.plot_report import write_plot_report

            write_plot_report(project, tmp / "report.html", scans=scans, comparison=comparison)
        except Exception as exc:  # a report must never lose the result
            log.warning("could not write the report: %s", exc)
    # the project file was saved inside the temporary folder: point it at its final place
    project.path = out / "project.json"
    json_path = out / Path(json_path).name
    print(f"{'pair':32} {'auto std':>9} {'VOPs':>5} {'manual std':>11} {'targets':>7} {'rot diff':>9} {'shift':>8}")
    failed = []
    for p in comparison["pairs"]:
        def cell(side):
            if side["status"] != "ok":
                return "failed"
            v = side.get("icp_std_m")
            return "n/a" if v is None else f"{100 * v:.2f} cm"

        rot = "-" if p["rotation_difference_deg"] is None else f"{p['rotation_difference_deg']:.3f} deg"
        shift = "-" if p["translation_difference_m"] is None else f"{100 * p['translation_difference_m']:.1f} cm"
        matched = p["auto"]["matched"] if p["auto"]["matched"] is not None else "-"
        targets = p["manual"]["targets"] if p["manual"]["targets"] is not None else "-"
        print(f"{p['moving'] + ' -> ' + p['reference']:32} {cell(p['auto']):>9} {str(matched):>5} "
              f"{cell(p['manual']):>11} {str(targets):>7} {rot:>9} {shift:>8}")
        for side in ("auto", "manual"):
            if p[side]["status"] != "ok":
                failed.append(f"{p['moving']} -> {p['reference']} {side}: {p[side].get('reason') or 'failed'}")
    for line in failed:
        print(f"  failed: {line}")
    a, m = comparison["auto_target_residual_m"], comparison["manual_target_residual_m"]
    fmt = lambda v: "n/a" if v is None else f"{100 * v:.2f} cm"  # noqa: E731
    print(f"average target distance residual: auto {fmt(a)}, manual {fmt(m)}"
          + ("" if not comparison.get("target_residual_note") else f" ({comparison['target_residual_note']})"))
    if (out / "report.html").exists():
        print(f"report: {shown(out) / 'report.html'}")
    args.reporter.done("", json_path)
    say(f"comparison: {json_path}" if not failed else f"{len(failed)} registrations failed -> {json_path}", args, err=bool(failed))
    return 0 if not failed else 1


def cmd_targets(args: argparse.Namespace) -> int:
    from ..engine.core.atomic import check_output_file
    from ..engine.io import read_scan
    from ..engine.io.base import check_readable
    from ..engine.tls.manual import detect_reflectors, match_detected_to_known, read_targets_csv, write_targets_csv

    for p in args.scans:
        check_readable(p)
    check_output_file(args.out, inputs=args.scans + ([args.known] if args.known else []), suffixes=(".csv", ".txt"))
    known = read_targets_csv(args.known) if args.known else {}
    found: dict[str, dict[str, np.ndarray]] = {}
    for k, path in enumerate(args.scans):
        args.reporter(k / len(args.scans), f"detecting reflectors in {Path(path).name}")
        scan = read_scan(path)
        detected = detect_reflectors(scan)
        name = Path(path).name
        if name in known:
            found[name] = match_detected_to_known(detected, known[name], args.max_distance)
        else:
            found[name] = {f"R{k + 1}": d.centre for k, d in enumerate(detected)}
        print(f"{name}: {len(detected)} reflectors detected" + (f", {len(found[name])} named after known targets" if name in known else ""))
    args.reporter.close()
    write_targets_csv(args.out, found)
    args.reporter.done("", args.out)
    say(f"targets: {args.out} (check them, rename to shared ids across scans, then use --targets)", args)
    return 0
