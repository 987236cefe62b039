"""The ``forestreg`` command line.

Every command is a thin wrapper over the engine's API; none holds algorithm code. Progress goes
to stderr as a bar, results to files, and the exit status says how it went: 0 ok, 1 a registration
that failed (with its reason in ``result.json``), 2 bad input or usage.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import logging
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

log = logging.getLogger("forestreg")

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "ft": 0.3048, "usft": 1200.0 / 3937.0}


# ----------------------------------------------------------------------------- helpers


def _floats(text: str, count: Optional[int] = None, what: str = "value") -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.replace(";", ",").split(",") if v.strip())
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{what}: {text!r} is not a comma-separated list of numbers") from exc
    if count is not None and len(values) != count:
        raise argparse.ArgumentTypeError(f"{what}: expected {count} numbers, got {text!r}")
    return values


class ProgressBar:
    """A tqdm bar on stderr fed by the engine's ``progress(fraction, message)`` callback."""

    def __init__(self, enabled: bool, desc: str) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.desc = desc
            self.bar = tqdm(total=1000, desc=desc, file=sys.stderr, bar_format="{desc} {percentage:3.0f}%|{bar:30}| {elapsed}", leave=True)

    def __call__(self, fraction: float, message: str) -> None:
        if self.bar is None:
            return
        self.bar.n = int(round(1000 * min(max(fraction, 0.0), 1.0)))
        self.bar.set_description_str(f"{self.desc}: {message[:40]:40}", refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _params_from_args(args: argparse.Namespace):
    from .engine.params import load_params
    from .engine.tls.params import RegistrationParams

    params = load_params(args.params).registration if args.params else RegistrationParams()
    changes = {}
    if args.dr is not None:
        changes["vop_radius_m"] = args.dr
    if args.dh is not None:
        changes["slice_offsets_m"] = tuple(args.dh)
    if getattr(args, "dc", None) is not None:
        changes["max_range_m"] = args.dc
    return params.replace(**changes) if changes else params


def _write_vops_csv(path: Path, xy: np.ndarray, z: np.ndarray, lsf_to_file: np.ndarray, radius: np.ndarray, support: np.ndarray, matched_with: Sequence[int]) -> None:
    from .engine.core.atomic import write_text_atomic

    pts = np.column_stack([xy, z, np.ones(len(xy))]) @ lsf_to_file.T if len(xy) else np.zeros((0, 4))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["id", "x", "y", "z", "radius_m", "support_points", "matched_with"])
    for k in range(len(xy)):
        w.writerow([k, f"{pts[k, 0]:.4f}", f"{pts[k, 1]:.4f}", f"{pts[k, 2]:.4f}", f"{radius[k]:.3f}", int(support[k]), "" if matched_with[k] < 0 else matched_with[k]])
    write_text_atomic(path, buf.getvalue())


# ----------------------------------------------------------------------------- commands


def cmd_register(args: argparse.Namespace) -> int:
    from .engine.core.atomic import write_text_atomic
    from .engine.io import read_scan, write_scan
    from .engine.tls.pair import register
    from .engine.report.figures import pair_figure
    from .engine.core.transform import format_matrix

    params = _params_from_args(args)
    positions = args.scanner_position or []
    if len(positions) > 2:
        raise argparse.ArgumentTypeError("--scanner-position is given at most twice (reference, then moving)")
    scale = UNITS[args.units]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    reference = read_scan(args.reference, scanner_position=positions[0] if len(positions) > 0 else None, unit_scale=scale)
    moving = read_scan(args.moving, scanner_position=positions[1] if len(positions) > 1 else None, unit_scale=scale)
    read_s = time.perf_counter() - t0
    ups = [np.array(u) for u in (args.up or [])]
    if len(ups) > 2:
        raise argparse.ArgumentTypeError("--up is given at most twice (reference, then moving)")
    bar = ProgressBar(not args.quiet, "register")
    try:
        result = register(
            reference, moving, params, progress=bar,
            reference_up=ups[0] if len(ups) > 0 else None, moving_up=ups[1] if len(ups) > 1 else None,
        )
    finally:
        bar.close()
    summary = result.to_dict()
    summary["timings"] = {"read": read_s, **summary["timings"]}
    summary["reference_file"] = str(Path(args.reference).resolve())
    summary["moving_file"] = str(Path(args.moving).resolve())
    det = result.details
    if det is not None and det.chosen is not None:
        att = det.chosen
        ref_match = np.full(len(att.reference_vops), -1)
        mov_match = np.full(len(att.moving_vops), -1)
        if att.match is not None:
            ref_match[att.match.matched_pairs[:, 0]] = att.match.matched_pairs[:, 1]
            mov_match[att.match.matched_pairs[:, 1]] = att.match.matched_pairs[:, 0]
        for scan, prep, vops, matched, name in (
            (reference, det.reference, att.reference_vops, ref_match, "reference_vops.csv"),
            (moving, det.moving, att.moving_vops, mov_match, "moving_vops.csv"),
        ):
            lsf_to_file = scan.local_to_file_matrix() @ np.linalg.inv(prep.local_to_lsf)
            _write_vops_csv(out / name, vops.xy, vops.z, lsf_to_file, vops.radius, vops.support, matched)
        try:
            pair_figure(result, out / "registration.png")
        except Exception as exc:  # a figure must never lose the result
            log.warning("could not draw the figure: %s", exc)
    if result.ok:
        write_text_atomic(out / "transform.txt", format_matrix(result.matrix))
        if args.write_registered:
            write_scan(moving, out / f"{moving.name}_registered.laz", matrix=result.matrix)
    write_text_atomic(out / "result.json", json.dumps(summary, indent=2) + "\n")
    if result.ok:
        icp = result.icp
        print(
            f"ok: {result.matched} matched VOPs ({result.reference_vops} / {result.moving_vops}), "
            f"ICP std {1000 * icp.std_m:.1f} mm, fitness {icp.fitness:.2f} -> {out / 'result.json'}"
        )
        return 0
    print(f"failed: {result.reason} -> {out / 'result.json'}", file=sys.stderr)
    return 1


def _write_keypoints_csv(path: Path, keypoints, local_to_file: np.ndarray, matched_with: np.ndarray) -> None:
    """Keypoints in file coordinates: id, x, y, z (on the DEM), peak_z, cluster_size, matched_with."""
    from .engine.core.atomic import write_text_atomic

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["id", "x", "y", "z", "peak_z", "cluster_size", "matched_with"])
    xyz = keypoints.xyz @ local_to_file[:3, :3].T + local_to_file[:3, 3]
    peak = keypoints.peak_z + local_to_file[2, 3]
    for i, (p, z, n, m) in enumerate(zip(xyz, peak, keypoints.cluster_sizes, matched_with)):
        w.writerow([i, f"{p[0]:.3f}", f"{p[1]:.3f}", f"{p[2]:.3f}", f"{z:.3f}", int(n), int(m)])
    write_text_atomic(path, buf.getvalue())


def cmd_coregister(args: argparse.Namespace) -> int:
    """Co-register a ground-based cloud onto a UAV cloud by canopy keypoints (System B)."""
    from .engine.core.atomic import write_text_atomic
    from .engine.coreg.coregister import coregister
    from .engine.io import read_scan
    from .engine.report.coregistration_report import write_coregistration_report
    from .engine.core.transform import format_matrix

    scale = UNITS[args.units]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ground = read_scan(args.ground, unit_scale=scale)
    uav = read_scan(args.uav, unit_scale=scale)
    read_s = time.perf_counter() - t0
    params = _coregistration_params(args)
    bar = ProgressBar(not args.quiet, "coregister")
    try:
        result = coregister(ground, uav, params, progress=bar)
    finally:
        bar.close()
    summary = result.to_dict()
    summary["timings"] = {"read_s": read_s, **summary["timings"]}
    summary["ground_file"] = str(Path(args.ground).resolve())
    summary["uav_file"] = str(Path(args.uav).resolve())
    summary["distance_threshold_m"] = params.matching.distance_threshold_m
    pairs = result.matched_after_icp if result.matched_after_icp is not None else (
        result.match.pairs if result.match is not None else np.zeros((0, 2), dtype=int))
    for scan, kp, column, other, name in (
        (ground, result.ground_keypoints, 0, 1, "keypoints_ground.csv"),
        (uav, result.uav_keypoints, 1, 0, "keypoints_uav.csv"),
    ):
        if kp is None:
            continue
        matched = np.full(len(kp), -1)
        if len(pairs):
            matched[pairs[:, column]] = pairs[:, other]
        _write_keypoints_csv(out / name, kp, scan.local_to_file_matrix(), matched)
    if result.ground_keypoints is not None:
        try:
            write_coregistration_report(result, out, ground.points, uav.points)
        except Exception as exc:  # a figure must never lose the result
            log.warning("could not draw the figure: %s", exc)
    if result.ok:
        write_text_atomic(out / "transform.txt", format_matrix(result.matrix))
    write_text_atomic(out / "result.json", json.dumps(summary, indent=2) + "\n")
    if result.ok:
        icp = result.icp
        print(
            f"ok: {result.n_matched} keypoints matched ({result.matching_percentage:.0f} % of "
            f"{len(result.ground_keypoints)} / {len(result.uav_keypoints)}), mean residual "
            f"{100 * summary['residuals_m']['mean']:.1f} cm, ICP fitness {icp.fitness:.2f} -> {out / 'result.json'}"
        )
        return 0
    print(f"failed: {result.reason} -> {out / 'result.json'}", file=sys.stderr)
    return 1


def _coregistration_params(args: argparse.Namespace):
    """Co-registration parameters: the defaults with the command line's options."""
    import dataclasses

    from .engine.coreg.coregister import CoregistrationParams
    from .engine.coreg.keypoints import KeypointParams
    from .engine.coreg.matching import MatchingParams

    kp: dict = {}
    mt: dict = {}
    if args.min_cluster_size is not None:
        kp["min_cluster_size"] = args.min_cluster_size
    if args.voxel is not None:
        kp["voxel_m"] = args.voxel
    if args.distance_threshold is not None:
        mt["distance_threshold_m"] = args.distance_threshold
    return CoregistrationParams(
        keypoints=dataclasses.replace(KeypointParams(), **kp), matching=dataclasses.replace(MatchingParams(), **mt)
    )


def _read_matrix(path: str) -> np.ndarray:
    """A 4x4 matrix from a text file (16 numbers, row by row), or result.json's ``matrix``."""
    from .engine.core.errors import ParameterError

    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ParameterError(f"cannot read the transform {path}: {exc}") from exc
    try:
        if text.lstrip().startswith("{"):
            m = json.loads(text).get("matrix")
            if m is None:
                raise ParameterError(f"{path}: the result holds no matrix (the co-registration failed)")
            matrix = np.asarray(m, dtype=np.float64)
        else:
            matrix = np.asarray(text.split(), dtype=np.float64).reshape(4, 4)
    except (ValueError, json.JSONDecodeError) as exc:
        raise ParameterError(f"{path}: not a 4x4 matrix ({exc})") from exc
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ParameterError(f"{path}: not a finite 4x4 matrix")
    r = matrix[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or not np.allclose(matrix[3], [0, 0, 0, 1]):
        raise ParameterError(f"{path}: not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    return matrix


def cmd_fuse(args: argparse.Namespace) -> int:
    """Fuse a ground-based and a UAV cloud (redundancy and noise removal) into one labelled cloud."""
    from .engine.coreg.fusion import FusionParams, fuse_scans, write_fused
    from .engine.io import read_scan

    scale = UNITS[args.units]
    matrix = _read_matrix(args.transform) if args.transform else np.eye(4)
    ground = read_scan(args.ground, unit_scale=scale)
    uav = read_scan(args.uav, unit_scale=scale)
    kw = {}
    if args.epsilon is not None:
        kw["redundancy_distance_m"] = args.epsilon
    if args.cube is not None:
        kw["cube_side_m"] = args.cube
    params = FusionParams(**kw)
    bar = ProgressBar(not args.quiet, "fuse")
    try:
        result = fuse_scans(ground, uav, matrix, params, progress=bar)
    finally:
        bar.close()
    write_fused(args.out, result, origin_shift=uav.origin_shift)
    for source, c in result.counts.items():
        print(f"{source}: {c['input']:,} in, {c['redundant']:,} redundant, {c['noise']:,} noise, {c['kept']:,} kept")
    print(f"wrote {len(result.points):,} points to {args.out}")
    return 0


def cmd_trees(args: argparse.Namespace) -> int:
    """Detect, segment and measure the trees of a ground-based or fused cloud (System B)."""
    import dataclasses

    from .engine.io import read_scan
    from .engine.trees.inventory import TreeParams, measure_trees

    cloud = read_scan(args.cloud, unit_scale=UNITS[args.units])
    if args.transform:
        cloud = cloud.transformed(_read_matrix(args.transform))
    params = TreeParams()
    if args.no_cylinders:
        params = dataclasses.replace(params, cylinder_models=False)
    bar = ProgressBar(not args.quiet, "trees")
    try:
        inventory = measure_trees(cloud.points, params, progress=bar, origin_shift=cloud.origin_shift)
    finally:
        bar.close()
    out = Path(args.out)
    path = inventory.write(out, cloud.points, report=not args.no_report)
    n_flagged = sum(1 for t in inventory.trees if t.flags)
    print(f"{len(inventory.trees)} trees ({n_flagged} flagged as incomplete) -> {path}")
    if args.field:
        return main(["evaluate", str(path), args.field, "--out", str(out / "evaluation")])
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Compare tree tables with field records: R2, RMSE, rRMSE per parameter (paper table 3)."""
    from .engine.trees.evaluate import evaluate, read_tree_table, write_evaluation

    field = read_tree_table(args.field)
    runs = {}
    named = [(args.name or Path(args.trees).parent.name or "run", args.trees)]
    for item in args.also or []:
        name, sep, path = item.partition("=")
        if not sep:
            name, path = Path(item).parent.name or f"run{len(named) + 1}", item
        named.append((name, path))
    for name, path in named:
        if name in runs:
            raise argparse.ArgumentTypeError(f"two runs are named {name!r}: name them with NAME=PATH")
        runs[name] = evaluate(read_tree_table(path), field, by=args.by, max_distance_m=args.max_distance)
    paths = write_evaluation(args.out, runs)
    for name, ev in runs.items():
        d = ev.detection
        figures = ", ".join(
            f"{p} R2 {st.r2:.2f} rRMSE {st.rrmse_percent:.1f} %" for p, st in ev.stats.items() if st.n >= 2
        )
        print(f"{name}: {d.matched} of {d.field_trees} field trees matched; {figures}")
    print(f"-> {paths['csv']}, {paths['html']}")
    return 0


def _project_from_args(args: argparse.Namespace):
    """A new project from the scans, centre, tilted marks, targets and parameters on the command line."""
    from .engine.tls.project import Project

    if len(args.scans) == 1 and Path(args.scans[0]).suffix.lower() == ".e57":
        from .engine.tls.plot import project_from_e57

        project = project_from_e57(args.scans[0])
        project.params = _params_from_args(args)
    else:
        project = Project(name=Path(args.out).name if getattr(args, "out", None) else "plot", params=_params_from_args(args))
        for path in args.scans:
            project.add_scan(path)
    names = {Path(p).name: s.name for p, s in zip(args.scans, project.scans)} if len(args.scans) == len(project.scans) else {}
    if args.centre:
        centre = names.get(Path(args.centre).name, args.centre)
        project.scan(centre)
        project.centre = centre
    for item in ",".join(args.tilted or []).split(","):
        if not item.strip():
            continue
        tilted, _, partner = item.partition(":")
        entry = project.scan(names.get(Path(tilted).name, tilted))
        entry.tilted = True
        if partner:
            entry.level_partner = project.scan(names.get(Path(partner).name, partner)).name
    _survey_inputs(project, args, names)
    if getattr(args, "targets", None):
        from .engine.tls.manual import read_targets_csv

        for scan_name, targets in read_targets_csv(args.targets).items():
            if project.has_scan(scan_name):
                project.scan(scan_name).targets = targets
            else:
                log.warning("targets for %s: no such scan in the plot", scan_name)
    return project


def _survey_inputs(project, args: argparse.Namespace, names: dict) -> None:
    """Scanner positions (--positions CSV) and prior poses (--prior-poses) into the project."""
    from .engine.core.errors import ParameterError
    from .engine.tls.survey import read_positions_csv, read_prior_poses

    def entry(name: str):
        try:
            return project.scan(names.get(Path(name).name, name))
        except KeyError as exc:
            raise ParameterError(str(exc.args[0])) from None

    if getattr(args, "positions", None):
        for name, xyz in read_positions_csv(args.positions).items():
            entry(name).scanner_position = xyz
    if getattr(args, "prior_poses", None):
        for name, pose in read_prior_poses(args.prior_poses).items():
            entry(name).prior_pose = pose
    for name in ",".join(getattr(args, "fixed", None) or []).split(","):
        if name.strip():
            entry(name.strip())


def _run_project(project, out: Path, args: argparse.Namespace) -> int:
    from .engine.tls.plot import ScanCache, add_neighbour_links, adjust_poses, register_project, write_merged, write_poses

    scans = ScanCache(project)
    bar = ProgressBar(not args.quiet, "plot")
    try:
        if getattr(args, "pairs", None):
            from .engine.tls.survey import SurveyParams, parse_pairs, register_survey

            pairs, distance = parse_pairs(args.pairs)
            names = {s.name: s.name for s in project.scans} | {Path(s.path).name: s.name for s in project.scans}
            fixed = tuple(names.get(n.strip(), n.strip()) for n in ",".join(getattr(args, "fixed", None) or []).split(",") if n.strip())
            outcome = register_survey(project, SurveyParams(pairs=pairs, max_distance_m=distance, fixed=fixed), rerun=getattr(args, "rerun", False), progress=bar, scans=scans)
        else:
            outcome = register_project(project, rerun=getattr(args, "rerun", False), progress=bar, scans=scans)
        if getattr(args, "loops", None) and not getattr(args, "pairs", None):
            added = add_neighbour_links(project, args.loops)
            if added:
                log.info("closing %d loops between neighbouring scans", len(added))
                register_project(project, progress=bar, scans=scans)
    finally:
        bar.close()
    adjusted = adjust_poses(project, scans) if not getattr(args, "pairs", None) else project.adjustment
    if project.path is not None:
        project.save()
    write_poses(project, out, outcome)
    try:
        from .engine.report.plot_report import write_plot_report

        write_plot_report(project, out / "report.html", scans=scans)
    except ImportError:  # pragma: no cover - report module optional during development
        pass
    if getattr(args, "merged", None):
        count = write_merged(project, args.merged, scans)
        print(f"merged {count} points into {args.merged}")
    if getattr(args, "registered_dir", None):
        from .engine.tls.plot import write_registered_scans

        count = write_registered_scans(project, args.registered_dir, scans)
        print(f"wrote {count} registered scans to {args.registered_dir}")
    if getattr(args, "e57_out", None):
        from .engine.tls.plot import write_registered_e57

        count = write_registered_e57(project, args.e57_out, scans)
        print(f"wrote {count} registered scans with their poses to {args.e57_out}")
    from .engine.tls.plot import pose_uncertainty

    sigma = pose_uncertainty(project)
    for name, status in outcome.status.items():
        extra = f" - {outcome.reasons[name]}" if name in outcome.reasons else ""
        link = project.link_of(name)
        onto = f" onto {link.reference}" if link is not None and status == "ok" else ""
        u = sigma.get(name) if status == "ok" else None
        if u and u.get("translation_m") is not None and u.get("rotation_deg") is not None:
            onto += f" (1 sigma {100 * u['translation_m']:.1f} cm, {u['rotation_deg']:.3f} deg)"
        print(f"{name}: {status}{onto}{extra}")
    dropped = (project.adjustment or {}).get("dropped") or []
    for d in dropped:
        print(f"dropped link {d['moving']} -> {d['reference']}: {d['reason']}")
    if adjusted:
        worst = max((r["after"]["translation_m"] for r in adjusted["links"]), default=0.0)
        print(f"global adjustment over {len(adjusted['links'])} links: largest link residual {100 * worst:.1f} cm")
    print(f"poses: {out / 'poses.json'}")
    return 0 if not outcome.failed else 1


def _check_survey_options(args: argparse.Namespace) -> None:
    """Bad --pairs / --positions / --prior-poses: one line and exit 2, before any work."""
    from .engine.tls.survey import parse_pairs, read_positions_csv, read_prior_poses

    if getattr(args, "pairs", None):
        parse_pairs(args.pairs)
    if getattr(args, "positions", None):
        read_positions_csv(args.positions)
    if getattr(args, "prior_poses", None):
        read_prior_poses(args.prior_poses)


def cmd_plot(args: argparse.Namespace) -> int:
    _check_survey_options(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    project = _project_from_args(args)
    project.save(out / "project.json")
    return _run_project(project, out, args)


def cmd_project(args: argparse.Namespace) -> int:
    from .engine.tls.project import Project

    if args.action == "create":
        _check_survey_options(args)
        project = _project_from_args(args)
        path = project.save(args.project)
        print(f"created {path} with {len(project.scans)} scans, centre {project.centre}")
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
        if args.extra:
            project.add_link(args.moving, args.reference, vop_radius_m=args.dr)
        else:
            project.set_link(args.moving, args.reference, vop_radius_m=args.dr)
        project.save()
        print(f"linked {args.moving} -> {args.reference}{' (extra link)' if args.extra else ''}")
        return 0
    out = Path(args.out) if args.out else project.path.parent
    _check_survey_options(args)
    return _run_project(project, out, args)


def cmd_compare(args: argparse.Namespace) -> int:
    from .engine.tls.compare import compare_auto_manual, write_comparison
    from .engine.tls.plot import ScanCache, write_poses

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    project = _project_from_args(args)
    project.save(out / "project.json")
    scans = ScanCache(project)
    bar = ProgressBar(not args.quiet, "compare")
    try:
        comparison = compare_auto_manual(project, scans=scans, progress=bar)
    finally:
        bar.close()
    write_poses(project, out)
    json_path, _ = write_comparison(comparison, out)
    try:
        from .engine.report.plot_report import write_plot_report

        write_plot_report(project, out / "report.html", scans=scans, comparison=comparison)
    except ImportError:  # pragma: no cover - report module optional during development
        pass
    print(f"{'pair':32} {'auto std':>9} {'VOPs':>5} {'manual std':>11} {'targets':>7} {'rot diff':>9} {'shift':>8}")
    for p in comparison["pairs"]:
        def cm(v):
            return "failed" if v is None else f"{100 * v:.2f} cm"

        rot = "-" if p["rotation_difference_deg"] is None else f"{p['rotation_difference_deg']:.3f} deg"
        shift = "-" if p["translation_difference_m"] is None else f"{100 * p['translation_difference_m']:.1f} cm"
        print(f"{p['moving'] + ' -> ' + p['reference']:32} {cm(p['auto']['icp_std_m']):>9} {str(p['auto']['matched']):>5} "
              f"{cm(p['manual']['icp_std_m']):>11} {str(p['manual']['targets']):>7} {rot:>9} {shift:>8}")
    a, m = comparison["auto_target_residual_m"], comparison["manual_target_residual_m"]
    fmt = lambda v: "n/a" if v is None else f"{100 * v:.2f} cm"  # noqa: E731
    print(f"average target distance residual: auto {fmt(a)}, manual {fmt(m)} -> {json_path}")
    failed = [p for p in comparison["pairs"] if p["auto"]["status"] != "ok" or p["manual"]["status"] != "ok"]
    return 0 if not failed else 1


def cmd_targets(args: argparse.Namespace) -> int:
    from .engine.io import read_scan
    from .engine.tls.manual import detect_reflectors, match_detected_to_known, read_targets_csv, write_targets_csv

    known = read_targets_csv(args.known) if args.known else {}
    found: dict[str, dict[str, np.ndarray]] = {}
    for path in args.scans:
        scan = read_scan(path)
        detected = detect_reflectors(scan)
        name = Path(path).name
        if name in known:
            found[name] = match_detected_to_known(detected, known[name], args.max_distance)
        else:
            found[name] = {f"R{k + 1}": d.centre for k, d in enumerate(detected)}
        print(f"{name}: {len(detected)} reflectors detected" + (f", {len(found[name])} named after known targets" if name in known else ""))
    write_targets_csv(args.out, found)
    print(f"targets: {args.out} (check them, rename to shared ids across scans, then use --targets)")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from .engine.simulate import simulate_plot

    positions = [tuple(_floats(p, 2, "--positions")) for p in args.positions.split(";")] if args.positions else [(0.0, 0.0), (10.0, 0.0)]
    tilted = {}
    for item in args.tilt or []:
        index, _, deg = item.partition(":")
        tilted[int(index)] = float(deg or 30.0)
    bar = ProgressBar(not args.quiet, "simulate")
    try:
        plot = simulate_plot(
            args.preset,
            positions,
            out_dir=Path(args.out),
            seed=args.seed,
            angular_step_deg=args.step,
            tilted=tilted or None,
            size_m=args.size,
            progress=bar,
        )
    finally:
        bar.close()
    for s in plot.scans:
        print(f"{s.scan.name}: {len(s.scan)} points")
    print(f"wrote {len(plot.scans)} scans and truth.json to {args.out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """System A: a simulated TLS pair registered from trunk shadows; System B: a simulated plot seen
    from the ground and from a UAV, co-registered, fused and measured. Both against the truth."""
    out = Path(args.out)
    codes = []
    if args.system in ("a", "both"):
        codes.append(_demo_system_a(out, args))
    if args.system in ("b", "both"):
        codes.append(_demo_system_b(out / "system_b", args))
    return max(codes)


def _demo_system_a(out: Path, args: argparse.Namespace) -> int:
    """Simulate a mixed forest pair 12 m apart, register it, and compare with the truth."""
    from .engine.simulate import relative_pose, simulate_plot
    from .engine.core.transform import rigid_errors

    data = out / "scans"
    data.mkdir(parents=True, exist_ok=True)
    print(f"System A: simulating a '{args.preset}' plot with two scans 12 m apart in {data} ...")
    plot = simulate_plot(args.preset, [(0.0, 0.0), (12.0, 3.0)], out_dir=data, seed=args.seed, angular_step_deg=args.step, size_m=50.0)
    names = [s.scan.name for s in plot.scans]
    code = main(["register", str(data / f"{names[0]}.laz"), str(data / f"{names[1]}.laz"), "--out", str(out / "registration")] + (["--quiet"] if args.quiet else []))
    result = json.loads((out / "registration" / "result.json").read_text())
    if result["matrix"] is not None:
        truth = relative_pose(plot, names[0], names[1])
        rot, trans = rigid_errors(np.array(result["matrix"]), truth)
        print(f"against the simulator's truth: rotation error {rot:.4f} deg, translation error {100 * trans:.2f} cm")
        print(f"figure: {out / 'registration' / 'registration.png'}")
    return code


def _demo_system_b(out: Path, args: argparse.Namespace) -> int:
    """A 28 m plot: merged TLS scans (ground-based, own frame, turned 120 deg and shifted 7 m) and
    a UAV flight at 86 m; co-register, fuse, measure the trees ground-only and fused, and
    evaluate both against the simulator's trees (the 'field data')."""
    from .engine.io import write_scan
    from .engine.simulate.platforms import simulate_coregistration_case
    from .engine.core.transform import rigid_errors

    quiet = ["--quiet"] if args.quiet else []
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    print(f"System B: simulating a plot seen by TLS and by a UAV in {data} ...")
    case = simulate_coregistration_case(
        "planted_conifer", seed=args.seed, size_m=28.0, ground_platform="tls", ground_extent_m=18.0,
        heading_deg=120.0, offset_m=(5.0, -5.0, 1.0), uav_density_scale=0.5, tls_step_deg=0.3,
    )
    write_scan(case.ground, data / "ground.laz")
    write_scan(case.uav, data / "uav.laz")
    field = data / "field.csv"
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["tree_id", "x", "y", "dbh_m", "height_m"])
    for t in case.scene.trees:
        if abs(t.x) < 9.0 and abs(t.y) < 9.0:
            w.writerow([f"T{t.id}", f"{t.x + case.world_offset[0]:.3f}", f"{t.y + case.world_offset[1]:.3f}", f"{t.dbh_m:.4f}", f"{t.height_m:.3f}"])
    field.write_text(buf.getvalue())
    code = main(["coregister", str(data / "ground.laz"), str(data / "uav.laz"), "--out", str(out / "coregistration")] + quiet)
    if code != 0:
        return code
    result = json.loads((out / "coregistration" / "result.json").read_text())
    rot, trans = rigid_errors(np.array(result["matrix"]), case.matrix)
    print(f"against the simulator's truth: rotation error {rot:.4f} deg, translation error {100 * trans:.2f} cm")
    transform = str(out / "coregistration" / "transform.txt")
    main(["fuse", str(data / "ground.laz"), str(data / "uav.laz"), "--transform", transform, "--out", str(out / "fused.laz")] + quiet)
    main(["trees", str(data / "ground.laz"), "--transform", transform, "--out", str(out / "trees_ground")] + quiet)
    main(["trees", str(out / "fused.laz"), "--out", str(out / "trees_fused")] + quiet)
    main(["evaluate", str(out / "trees_ground" / "trees.csv"), str(field), "--name", "ground",
          "--also", f"fused={out / 'trees_fused' / 'trees.csv'}", "--out", str(out / "evaluation")])
    print(f"reports: {out / 'coregistration' / 'report.html'}, {out / 'trees_fused' / 'report.html'}, "
          f"{out / 'evaluation' / 'report.html'}")
    return 0


def cmd_gui(args: argparse.Namespace) -> int:
    try:
        from .ui.app import main as gui_main
    except ImportError as exc:
        print(f"forestreg: error: the GUI needs the 'gui' extras (pip install 'forestreg[gui]'): {exc}", file=sys.stderr)
        return 2
    return gui_main(list(args.gui_args))


def cmd_params(args: argparse.Namespace) -> int:
    from .engine.params import ProductParams, load_params, params_toml

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


# ----------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(prog="forestreg", description="Marker-free registration of forest laser scans.")
    parser.add_argument("--version", action="version", version=f"forestreg {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log every step to stderr")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("register", help="register a moving scan onto a reference scan from trunk shadows")
    p.add_argument("reference", help="reference scan (LAS/LAZ/PLY/PCD/E57/XYZ)")
    p.add_argument("moving", help="moving scan, mapped onto the reference")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--dr", type=float, help="VOP radius D_r in metres (default: automatic)")
    p.add_argument("--dc", type=float, help="reduction radius D_c in metres (default 30)")
    p.add_argument("--dh", type=lambda s: _floats(s, what="--dh"), help="slice offsets dh in metres, comma-separated (default 0)")
    p.add_argument("--params", help="TOML parameter file ([registration] table; see 'forestreg params --toml')")
    p.add_argument(
        "--scanner-position", action="append", type=lambda s: _floats(s, 3, "--scanner-position"),
        metavar="X,Y,Z", help="scanner position in file coordinates: first for the reference, again for the moving scan (default: each file's origin)",
    )
    p.add_argument("--units", choices=sorted(UNITS), default="m", help="unit of the files' coordinates (default m)")
    p.add_argument(
        "--up", action="append", type=lambda s: _floats(s, 3, "--up"), metavar="X,Y,Z",
        help="the true vertical in a scan's own coordinates (from its inclination sensor): first for the reference, again for the moving scan (default: estimated from the data)",
    )
    p.add_argument("--write-registered", action="store_true", help="also write the moving scan transformed into the reference frame (LAZ)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_register)

    def add_plot_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--centre", help="the centre (root) scan: the project frame (default: the first scan)")
        p.add_argument("--tilted", action="append", metavar="SCAN[:PARTNER],...", help="tilted scans, each optionally with the level scan at the same spot")
        p.add_argument("--targets", help="targets CSV (scan,target,x,y,z in each scan's own coordinates)")
        p.add_argument("--dr", type=float, help="VOP radius D_r in metres for every link (default: automatic)")
        p.add_argument("--dc", type=float, help="reduction radius D_c in metres (default 30)")
        p.add_argument("--dh", type=lambda s: _floats(s, what="--dh"), help="slice offsets dh in metres, comma-separated")
        p.add_argument("--params", help="TOML parameter file")
        p.add_argument("--pairs", metavar="all|within:D|centre", help="register every pair (or those whose scanners stand within D m), solve a pose graph weighted by each pair's evidence, drop inconsistent links, state each pose's uncertainty")
        p.add_argument("--positions", metavar="CSV", help="scanner positions: CSV scan,x,y,z in each scan's file coordinates (default: the E57 pose, else found from the data)")
        p.add_argument("--prior-poses", metavar="FILE", help="prior poses to check links against: poses.json, JSON {scan: 4x4}, or CSV scan,x,y,z[,heading_deg] (GNSS/compass)")
        p.add_argument("--fixed", action="append", metavar="SCAN,...", help="scans held at their prior poses (with --pairs)")

    p = sub.add_parser("plot", help="register all scans of a plot (each to the centre scan, tilted ones to their level partner)")
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files, or one multi-scan E57 file")
    p.add_argument("--out", required=True, help="output folder: project.json, poses.json, <scan>.transform.txt, report.html")
    add_plot_options(p)
    p.add_argument("--merged", help="also write all registered scans into one LAZ with a scan_id per point")
    p.add_argument("--e57-out", help="also write the registered scans with their poses into one E57 file")
    p.add_argument("--registered-dir", help="also write each registered scan, in the centre scan's coordinates, as its own LAZ into this folder")
    p.add_argument("--loops", type=float, metavar="M", help="also link registered scans standing within M metres of each other, and adjust all poses globally")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("compare", help="register a plot automatically and from targets, and compare (the paper's tables 4 and 5)")
    p.add_argument("scans", nargs="+", metavar="SCAN", help="scan files, or one multi-scan E57 file")
    p.add_argument("--out", required=True, help="output folder: comparison.json/.csv, report.html, project.json, poses.json")
    add_plot_options(p)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("targets", help="detect reflector targets (bright small discs/cylinders) in scans with intensity")
    p.add_argument("scans", nargs="+", metavar="SCAN")
    p.add_argument("--out", required=True, help="targets CSV to write (scan,target,x,y,z)")
    p.add_argument("--known", help="approximate targets CSV: name detections after the nearest known target")
    p.add_argument("--max-distance", type=float, default=0.3, help="largest distance to a known target, metres (default 0.3)")
    p.set_defaults(func=cmd_targets)

    p = sub.add_parser("project", help="create, inspect, link and re-run a saved plot project")
    psub = p.add_subparsers(dest="action", required=True)
    q = psub.add_parser("create", help="create a project file from scans")
    q.add_argument("project", help="project file to write (.json)")
    q.add_argument("scans", nargs="+", metavar="SCAN")
    add_plot_options(q)
    q.set_defaults(func=cmd_project, out=None)
    q = psub.add_parser("show", help="print the scans, links and results of a project")
    q.add_argument("project")
    q.set_defaults(func=cmd_project)
    q = psub.add_parser("link", help="link MOVING to REFERENCE (replacing its link, or --extra for a loop)")
    q.add_argument("project")
    q.add_argument("moving")
    q.add_argument("reference")
    q.add_argument("--dr", type=float, help="VOP radius for this link")
    q.add_argument("--extra", action="store_true", help="add an extra link (closes a loop for the global adjustment)")
    q.set_defaults(func=cmd_project)
    q = psub.add_parser("run", help="register the project's scans (links that succeeded are kept unless --rerun)")
    q.add_argument("project")
    q.add_argument("--out", help="output folder (default: the project's folder)")
    q.add_argument("--rerun", action="store_true", help="run every link again")
    q.add_argument("--pairs", metavar="all|within:D|centre", help="register every pair (or those within D m), pose graph, inconsistent links dropped, uncertainty per pose")
    q.add_argument("--fixed", action="append", metavar="SCAN,...", help="scans held at their prior poses (with --pairs)")
    q.add_argument("--merged", help="also write all registered scans into one LAZ")
    q.add_argument("--e57-out", help="also write the registered scans with their poses into one E57 file")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=cmd_project)

    p = sub.add_parser("coregister", help="co-register a ground-based cloud onto a UAV cloud by canopy keypoints")
    p.add_argument("ground", help="ground-based cloud (merged TLS, backpack or handheld; LAS/LAZ/PLY/E57/...)")
    p.add_argument("uav", help="UAV LiDAR cloud of the same plot (the reference frame)")
    p.add_argument("--out", required=True, help="output folder (result.json, transform.txt, keypoints CSV, report)")
    p.add_argument("--min-cluster-size", type=int, help="HDBSCAN MinClusterSize (default: from the point density)")
    p.add_argument("--voxel", type=float, help="thinning voxel before clustering, m (default 0.3)")
    p.add_argument("--distance-threshold", type=float, help="D_thr for matched keypoints, m (default 1)")
    p.add_argument("--units", choices=sorted(UNITS), default="m", help="units of the input coordinates")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_coregister)

    p = sub.add_parser("fuse", help="fuse co-registered ground-based and UAV clouds (redundancy + noise removal)")
    p.add_argument("ground", help="ground-based cloud")
    p.add_argument("uav", help="UAV cloud (the output frame)")
    p.add_argument("--transform", help="transform.txt or result.json of `coregister` (p_uav = M @ p_ground); default identity")
    p.add_argument("--out", required=True, help="fused cloud (.laz/.las) with a per-point source label")
    p.add_argument("--epsilon", type=float, help="redundancy distance, m")
    p.add_argument("--cube", type=float, help="cube side of the redundancy search, m")
    p.add_argument("--units", choices=sorted(UNITS), default="m", help="units of the input coordinates")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_fuse)

    p = sub.add_parser("trees", help="detect and measure trees (DBH, height, crown, cylinder models) in a ground-based or fused cloud")
    p.add_argument("cloud", help="the cloud (LAS/LAZ/PLY/E57/...), ground included")
    p.add_argument("--out", required=True, help="output folder (trees.csv, stem_curves.csv, cylinders/, report.html)")
    p.add_argument("--transform", help="move the cloud first (transform.txt of `coregister`: into the UAV/field frame)")
    p.add_argument("--field", help="field records CSV: evaluate the trees against them into OUT/evaluation")
    p.add_argument("--no-cylinders", action="store_true", help="skip the cylinder models (faster; no volume)")
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    p.add_argument("--units", choices=sorted(UNITS), default="m", help="units of the input coordinates")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_trees)

    p = sub.add_parser("evaluate", help="compare trees.csv with field records: R2, RMSE, rRMSE per parameter (paper table 3)")
    p.add_argument("trees", help="trees.csv of `forestreg trees`")
    p.add_argument("field", help="field records CSV (tree_id, x, y and any of dbh_m/dbh_cm, height_m, ...)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--name", help="name of the first run (default: its folder name)")
    p.add_argument("--also", action="append", metavar="[NAME=]TREES", help="another run to show side by side, e.g. fused=fused/trees.csv")
    p.add_argument("--by", choices=("position", "id"), default="position", help="match trees by position or by id")
    p.add_argument("--max-distance", type=float, default=1.0, help="largest distance of a position match, m")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("simulate", help="simulate TLS scans of a synthetic forest plot with known poses")
    p.add_argument("preset", help="planted_conifer, mixed_temperate, rainforest, sloped or open_field")
    p.add_argument("--out", required=True, help="output folder (scan_XX.laz + truth.json)")
    p.add_argument("--positions", help="scanner positions 'x,y;x,y;...' in metres (default '0,0;10,0')")
    p.add_argument("--tilt", action="append", metavar="INDEX:DEG", help="tilt scan INDEX by DEG degrees (repeatable)")
    p.add_argument("--step", type=float, default=0.2, help="angular step in degrees (default 0.2)")
    p.add_argument("--size", type=float, default=60.0, help="plot side in metres (default 60)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("demo", help="simulated data through both systems (TLS pair; ground/UAV co-registration, fusion, trees), checked against the truth")
    p.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    p.add_argument("--preset", default="mixed_temperate")
    p.add_argument("--step", type=float, default=0.15, help="angular step of the simulated scans, degrees")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--system", choices=("a", "b", "both"), default="both", help="System A (TLS pair), B (ground/UAV, trees) or both")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("gui", help="the desktop GUI (--offscreen --project P --run --screenshot OUT.png for headless use)", add_help=False)
    p.add_argument("gui_args", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_gui)

    p = sub.add_parser("params", help="print every parameter of the product (or a TOML template: sections [registration], [coregistration], [fusion], [trees])")
    p.add_argument("--toml", action="store_true", help="print a TOML file of the values (the defaults, or those of --params)")
    p.add_argument("--params", help="a TOML parameter file to show merged over the defaults")
    p.set_defaults(func=cmd_params)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    from .engine.core.errors import ForestregError

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["gui"]:  # the GUI parses its own options
        return cmd_gui(argparse.Namespace(gui_args=argv[1:]))
    parser = build_parser()
    args = parser.parse_args(argv)
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except BrokenPipeError:  # output piped into head & co.
        return 0
    except ForestregError as exc:
        print(f"forestreg: error: {exc}", file=sys.stderr)
        return 2
    except argparse.ArgumentTypeError as exc:
        print(f"forestreg: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
