"""``forestreg coregister`` and ``forestreg fuse``: ground-based and UAV clouds (System B)."""

from __future__ import annotations

import argparse
import sys
from typing import Optional

from .common import Reporter, add_crs_option, add_units_params, number, product_params, run_outcome, say, shown


def add_parsers(sub) -> None:
    p = sub.add_parser("coregister", help="co-register a ground-based cloud onto a UAV cloud by canopy keypoints")
    p.add_argument("ground", help="ground-based cloud (merged TLS, backpack or handheld; LAS/LAZ/PLY/E57/...)")
    p.add_argument("uav", help="UAV LiDAR cloud of the same plot (the reference frame)")
    p.add_argument(
        "--out",
        required=True,
        help="output folder (result.json, transform.txt, keypoints CSV, report); replaced when the run completes",
    )
    p.add_argument(
        "--min-cluster-size",
        type=number("--min-cluster-size", minimum=2, integer=True),
        help="HDBSCAN MinClusterSize, at least 2 (default: from the point density)",
    )
    p.add_argument(
        "--voxel", type=number("--voxel", positive=True), help="thinning voxel before clustering, m (default 0.3)"
    )
    p.add_argument(
        "--distance-threshold",
        type=number("--distance-threshold", positive=True),
        help="D_thr for matched keypoints, m (default 1)",
    )
    add_crs_option(p, "result.json and layers.gpkg are in the UAV cloud's frame and take its CRS")
    add_units_params(p, "units of the input coordinates; results are written in the same unit", cmd_coregister)

    p = sub.add_parser("fuse", help="fuse co-registered ground-based and UAV clouds (redundancy + noise removal)")
    p.add_argument("ground", help="ground-based cloud")
    p.add_argument("uav", help="UAV cloud (the output frame)")
    p.add_argument(
        "--transform",
        help="transform.txt or result.json of `coregister` (p_uav = M @ p_ground, in the files' units); default identity",
    )
    p.add_argument(
        "--out",
        required=True,
        help="fused cloud to write (.laz/.las; never one of the inputs) with a per-point source label",
    )
    p.add_argument("--epsilon", type=number("--epsilon", positive=True), help="redundancy distance, m (default 0.01)")
    p.add_argument("--cube", type=number("--cube", positive=True), help="cube side of the redundancy search, m")
    add_crs_option(
        p, "the fused cloud (in the UAV cloud's frame) takes it; needed when the two files declare different CRSs"
    )
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
    return run_coregister(
        args.ground,
        args.uav,
        args.out,
        params=coregistration_params(args),
        units=args.units,
        reporter=args.reporter,
        crs=args.crs,
    )


def run_coregister(
    ground_path, uav_path, out, *, params=None, units: str = "m", reporter: Optional[Reporter] = None, crs=None
) -> int:
    """Co-register ``ground_path`` onto ``uav_path`` into the folder ``out``
    (:func:`forestreg.app.coregistration.coregister_clouds`) and print the outcome."""
    from ..app.coregistration import coregister_clouds

    reporter = reporter or Reporter("none", "coregister")
    if params is None:
        params = coregistration_params(argparse.Namespace())

    def steps(fraction: float, message: str = "") -> None:  # one line per step above a live bar
        reporter(fraction, message)
        if reporter.mode == "bar" and message.startswith("[") and sys.stderr.isatty():
            from tqdm import tqdm

            tqdm.write(message, file=sys.stderr)

    return print_coregister(
        run_outcome(
            reporter, coregister_clouds, ground_path, uav_path, out, params, units=units, crs=crs, progress=steps
        ),
        reporter,
    )


def print_coregister(outcome, reporter: Reporter) -> int:
    """The lines of a co-registration's outcome; returns the exit code."""
    out = outcome.out
    reporter.done("", out / "result.json")
    ns = argparse.Namespace(reporter=reporter)
    if outcome:
        if outcome.report is not None:
            print(f"report: {shown(out) / 'report.html'}")
        say(f"{outcome.line()} -> {shown(out) / 'result.json'}", ns)  # the last line: one-line summary
        return 0
    say(f"failed: {outcome.reason} -> {shown(out) / 'result.json'}", ns, err=True)
    return 1


def cmd_fuse(args: argparse.Namespace) -> int:
    return run_fuse(
        args.ground,
        args.uav,
        args.out,
        transform=args.transform,
        units=args.units,
        params=product_params(args).fusion,
        epsilon=args.epsilon,
        cube=args.cube,
        reporter=args.reporter,
        crs=args.crs,
    )


def run_fuse(
    ground_path,
    uav_path,
    out,
    *,
    transform=None,
    units: str = "m",
    epsilon=None,
    cube=None,
    params=None,
    reporter: Optional[Reporter] = None,
    crs=None,
) -> int:
    """Fuse two clouds into the LAS/LAZ ``out`` (:func:`forestreg.app.fusion.fuse_clouds`)."""
    from ..app.fusion import default_params, fuse_clouds

    reporter = reporter or Reporter("none", "fuse")
    kw = {}
    if epsilon is not None:
        kw["redundancy_distance_m"] = epsilon
    if cube is not None:
        kw["cube_side_m"] = cube
    params = (params or default_params()).replace(**kw)
    return print_fuse(
        run_outcome(
            reporter, fuse_clouds, ground_path, uav_path, out, params, transform=transform, units=units, crs=crs
        ),
        reporter,
    )


def print_fuse(outcome, reporter: Reporter) -> int:
    """The lines of a fusion's outcome; returns the exit code."""
    for source, c in outcome.sources.items():
        print(c.line(source))
    frame = getattr(outcome, "crs", None)
    for note in frame.notes if frame is not None else ():
        print(f"note: {note}")
    reporter.done("", outcome.out)
    say(f"wrote {outcome.points:,} points to {shown(outcome.out)}", argparse.Namespace(reporter=reporter))
    return 0
