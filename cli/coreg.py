"""``forestreg coregister`` and ``forestreg fuse``: ground-based and UAV clouds (System B)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Optional

import numpy as np

from .common import UNITS, Reporter, add_units_params, check_replaceable_point_file, log, number, product_params, say, shown


def add_parsers(sub) -> None:
    p = sub.add_parser("coregister", help="co-register a ground-based cloud onto a UAV cloud by canopy keypoints")
    p.add_argument("ground", help="ground-based cloud (merged TLS, backpack or handheld; LAS/LAZ/PLY/E57/...)")
    p.add_argument("uav", help="UAV LiDAR cloud of the same plot (the reference frame)")
    p.add_argument("--out", required=True, help="output folder (result.json, transform.txt, keypoints CSV, report); replaced when the run completes")
    p.add_argument("--min-cluster-size", type=number("--min-cluster-size", minimum=2, integer=True), help="HDBSCAN MinClusterSize, at least 2 (default: from the point density)")
    p.add_argument("--voxel", type=number("--voxel", positive=True), help="thinning voxel before clustering, m (default 0.3)")
    p.add_argument("--distance-threshold", type=number("--distance-threshold", positive=True), help="D_thr for matched keypoints, m (default 1)")
    add_units_params(p, "units of the input coordinates; results are written in the same unit", cmd_coregister)

    p = sub.add_parser("fuse", help="fuse co-registered ground-based and UAV clouds (redundancy + noise removal)")
    p.add_argument("ground", help="ground-based cloud")
    p.add_argument("uav", help="UAV cloud (the output frame)")
    p.add_argument("--transform", help="transform.txt or result.json of `coregister` (p_uav = M @ p_ground, in the files' units); default identity")
    p.add_argument("--out", required=True, help="fused cloud to write (.laz/.las; never one of the inputs) with a per-point source label")
    p.add_argument("--epsilon", type=number("--epsilon", positive=True), help="redundancy distance, m (default 0.01)")
    p.add_argument("--cube", type=number("--cube", positive=True), help="cube side of the redundancy search, m")
    add_units_params(p, "units of the input coordinates (and of the fused cloud)", cmd_fuse)


def coregistration_params(args: argparse.Namespace):
    """Co-registration parameters: the defaults (or ``--params``) with the command line's options."""
    base = product_params(args).coregistration
    kp: dict = {}
    mt: dict = {}
    if getattr(args, "min_cluster_size", None) is not None:
        kp["min_cluster_size"] = args.min_cluster_size
    if getattr(args, "voxel", None) is not None:
        kp["voxel_m"] = args.voxel
    if getattr(args, "distance_threshold", None) is not None:
        mt["distance_threshold_m"] = args.distance_threshold
    return base.replace(keypoints=base.keypoints.replace(**kp), matching=base.matching.replace(**mt))


def cmd_coregister(args: argparse.Namespace) -> int:
    return run_coregister(args.ground, args.uav, args.out, params=coregistration_params(args), units=args.units, reporter=args.reporter)


def run_coregister(ground_path, uav_path, out, *, params=None, units: str = "m", reporter: Optional[Reporter] = None) -> int:
    """Co-register ``ground_path`` onto ``uav_path``; the output folder ``out`` is a transaction."""
    from ..engine.core.atomic import check_output_folder, output_folder, write_text_atomic
    from ..engine.core.transform import format_matrix
    from ..engine.coreg.coregister import coregister
    from ..engine.io import read_scan
    from ..engine.io.tables import write_keypoints_csv
    from ..engine.report.samples import profile_sample
    from .common import run_summary

    reporter = reporter or Reporter("none", "coregister")
    if params is None:
        params = coregistration_params(argparse.Namespace())
    scale = UNITS[units]
    out = check_output_folder(out, "coregister", inputs=[ground_path, uav_path])
    # the scans are read inside the co-registration, which lets each full cloud go once thinned;
    # kept here: each scan's frame and the points its figure draws
    kept: dict = {"read_s": 0.0}

    def reader(path, role: str):
        def load():
            t0 = time.perf_counter()
            scan = read_scan(path, unit_scale=scale, with_intensity=False)  # the co-registration uses x, y, z alone
            kept["read_s"] += time.perf_counter() - t0
            kept[role], kept[role + "_profile"] = scan.without_points(), profile_sample(scan.points, role)
            return scan
        return load

    def steps(fraction: float, message: str = "") -> None:  # one line per step above a live bar
        reporter(fraction, message)
        if reporter.mode == "bar" and message.startswith("[") and sys.stderr.isatty():
            from tqdm import tqdm

            tqdm.write(message, file=sys.stderr)

    try:
        result = coregister(reader(ground_path, "ground"), reader(uav_path, "uav"), params, progress=steps)
    finally:
        reporter.close()
    ground, uav = kept["ground"], kept["uav"]
    summary, ok = run_summary(result, {"read_s": kept["read_s"]}, {"ground_file": ground_path, "uav_file": uav_path}, units, scale,
                              facts={"distance_threshold_m": params.matching.distance_threshold_m})
    pairs = result.matched_after_icp if result.matched_after_icp is not None else (
        result.match.pairs if result.match is not None else np.zeros((0, 2), dtype=int))
    with output_folder(out, "coregister") as tmp:
        for scan, kp, column, other, name in (
            (ground, result.ground_keypoints, 0, 1, "keypoints_ground.csv"),
            (uav, result.uav_keypoints, 1, 0, "keypoints_uav.csv"),
        ):
            if kp is None:
                continue
            matched = np.full(len(kp), -1)
            if len(pairs):
                matched[pairs[:, column]] = pairs[:, other]
            write_keypoints_csv(tmp / name, kp, scan.local_to_file_matrix(), matched, unit_scale=scale)
        if result.ground_keypoints is not None:
            try:
                from ..engine.report.coregistration_report import write_coregistration_report

                write_coregistration_report(result, tmp, kept["ground_profile"], kept["uav_profile"])
            except Exception as exc:  # a figure must never lose the result
                log.warning("could not draw the figure: %s", exc)
        if ok:
            write_text_atomic(tmp / "transform.txt", format_matrix(np.asarray(summary["matrix"])))
        write_text_atomic(tmp / "result.json", json.dumps(summary, indent=2) + "\n")
    reporter.done("", out / "result.json")
    ns = argparse.Namespace(reporter=reporter)
    if ok:
        if (out / "report.html").exists():
            print(f"report: {shown(out) / 'report.html'}")
        say(f"{result.summary()} -> {shown(out) / 'result.json'}", ns)  # the last line: one-line summary
        return 0
    say(f"failed: {summary['reason']} -> {shown(out) / 'result.json'}", ns, err=True)
    return 1


def cmd_fuse(args: argparse.Namespace) -> int:
    return run_fuse(args.ground, args.uav, args.out, transform=args.transform, units=args.units, params=product_params(args).fusion,
                    epsilon=args.epsilon, cube=args.cube, reporter=args.reporter)


def run_fuse(ground_path, uav_path, out, *, transform=None, units: str = "m", epsilon=None, cube=None,
             params=None, reporter: Optional[Reporter] = None) -> int:
    """Fuse two clouds into the LAS/LAZ ``out`` (refused when it is an input)."""
    from ..engine.core.atomic import check_output_file
    from ..engine.core.transform import read_matrix, to_metres
    from ..engine.coreg.fusion import FusionParams, fuse_files, write_fused
    from ..engine.io.base import check_readable

    reporter = reporter or Reporter("none", "fuse")
    scale = UNITS[units]
    check_readable(ground_path)
    check_readable(uav_path)
    out = check_output_file(out, inputs=[ground_path, uav_path, transform], suffixes=(".laz", ".las"))
    check_replaceable_point_file(out, "source", "fused cloud")
    matrix = to_metres(read_matrix(transform), scale) if transform else np.eye(4)
    kw = {}
    if epsilon is not None:
        kw["redundancy_distance_m"] = epsilon
    if cube is not None:
        kw["cube_side_m"] = cube
    params = (params or FusionParams()).replace(**kw)
    try:  # the ground-based cloud is read inside, and let go once merged: a scan's points less to hold
        result, shift = fuse_files(ground_path, uav_path, matrix, params, unit_scale=scale, progress=reporter)
    finally:
        reporter.close()
    write_fused(out, result, origin_shift=shift, unit_scale=scale)
    for source, c in result.counts.items():
        print(f"{source}: {c['input']:,} in, {c['redundant']:,} redundant, {c['noise']:,} noise, {c['kept']:,} kept")
    reporter.done("", out)
    say(f"wrote {len(result.points):,} points to {shown(out)}", argparse.Namespace(reporter=reporter))
    return 0
