"""``forestreg register``: one TLS pair from trunk shadows (System A)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .common import PARAMS_HELP, UNITS, Reporter, direction, floats, log, number, offsets, params_from_args, say, shown


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("register", help="register a moving scan onto a reference scan from trunk shadows")
    p.add_argument("reference", help="reference scan (LAS/LAZ/PLY/PCD/E57/XYZ)")
    p.add_argument("moving", help="moving scan, mapped onto the reference")
    p.add_argument("--out", required=True, help="output folder (new, empty, or an earlier register output: it is replaced when the run completes)")
    p.add_argument("--dr", type=number("--dr", positive=True), help="VOP radius D_r in metres (default: automatic)")
    p.add_argument("--dc", type=number("--dc", positive=True), help="reduction radius D_c in metres (default 30)")
    p.add_argument("--dh", type=offsets, help="slice offsets dh in metres, comma-separated (default 0)")
    p.add_argument("--params", help=PARAMS_HELP)
    p.add_argument(
        "--scanner-position", action="append", type=lambda s: floats(s, 3, "--scanner-position"),
        metavar="X,Y,Z", help="scanner position in file coordinates: first for the reference, again for the moving scan (default: each file's origin)",
    )
    p.add_argument("--units", choices=sorted(UNITS), default="m", help="unit of the files' coordinates (default m); results are written in the same unit")
    p.add_argument(
        "--up", action="append", type=direction("--up"), metavar="X,Y,Z",
        help="the true vertical in a scan's own coordinates (from its inclination sensor): first for the reference, again for the moving scan (default: estimated from the data)",
    )
    p.add_argument("--write-registered", action="store_true", help="also write the moving scan transformed into the reference frame (LAZ)")
    p.set_defaults(func=cmd_register, long_running=True)
    return p


def cmd_register(args: argparse.Namespace) -> int:
    from ..engine.core.errors import UsageError

    positions = args.scanner_position or []
    if len(positions) > 2:
        raise UsageError("--scanner-position is given at most twice (reference, then moving)")
    ups = [np.array(u) for u in (args.up or [])]
    if len(ups) > 2:
        raise UsageError("--up is given at most twice (reference, then moving)")
    return run_register(
        args.reference, args.moving, args.out, params=params_from_args(args), positions=positions, ups=ups,
        units=args.units, write_registered=args.write_registered, reporter=args.reporter,
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
) -> int:
    """Register ``moving_path`` onto ``reference_path`` and write the output folder ``out`` as a
    transaction. Returns the exit code (0 ok, 1 failed with a reason)."""
    from concurrent.futures import ThreadPoolExecutor

    from ..engine.core.atomic import check_output_folder, output_folder, write_text_atomic
    from ..engine.core.errors import UsageError
    from ..engine.io import read_scan, write_scan
    from ..engine.tls.params import RegistrationParams
    from .common import import_in_background, run_summary

    reporter = reporter or Reporter("none", "register")
    params = params or RegistrationParams()
    if Path(reference_path).resolve() == Path(moving_path).resolve():
        raise UsageError(f"REFERENCE and MOVING are the same file ({reference_path}): a scan cannot be registered onto itself")
    scale = UNITS[units]
    out = check_output_folder(out, "register", inputs=[reference_path, moving_path])

    def read(path, index: int):
        # the registration uses the coordinates alone: intensity only for the registered scan written
        return read_scan(path, scanner_position=positions[index] if len(positions) > index else None, unit_scale=scale,
                         with_intensity=write_registered and index == 1)

    # both scans are read, one after the other (the decompression is multi-core), while the
    # registration engine is imported
    early = ThreadPoolExecutor(1, thread_name_prefix="forestreg-read")
    pending = {0: early.submit(read, reference_path, 0), 1: early.submit(read, moving_path, 1)}  # popped when used: the scan's points are not held
    early.shutdown(wait=False)
    import_in_background(".engine.report.figures", kernels=True)
    from ..engine.core.transform import format_matrix
    from ..engine.io.tables import pair_vop_tables, write_vops_csv
    from ..engine.tls.pair import register
    from ..engine.tls.scanner_position import locate_scanner

    # each scan is located and checked in the thread that prepares it (one is read while the
    # other is prepared); the engine keeps only the prepared scans, and the moving scan's points
    # only when they are written out registered
    kept: dict = {}

    def reader(path, index: int, role: str):
        def load():
            job = pending.pop(index, None)
            scan = job.result() if job is not None else read(path, index)
            del job
            # no scanner position given and the file origin is not the scanner (project/UTM
            # exports): find it from the data, or refuse with the reason
            scan = locate_scanner(scan)
            check_near_scanner(scan, params.max_range_m, path, units)
            kept[role] = scan.without_points()
            if role == "moving" and write_registered:
                kept["registered_points"] = scan
            return scan
        return load

    try:
        result = register(
            reader(reference_path, 0, "reference"), reader(moving_path, 1, "moving"), params, progress=reporter,
            reference_up=ups[0] if len(ups) > 0 else None, moving_up=ups[1] if len(ups) > 1 else None,
        )
    finally:
        reporter.close()
    reference, moving = kept["reference"], kept["moving"]
    registered_points = kept.get("registered_points")
    read_s = sum(result.timings.get(f"read_{role}_s", 0.0) for role in ("reference", "moving"))
    summary, ok = run_summary(result, {"read_s": read_s}, {"reference_file": reference_path, "moving_file": moving_path}, units, scale,
                              matrix_keys=("matrix", "coarse_matrix"))
    with output_folder(out, "register") as tmp:
        for scan, to_file, vops, matched, name in pair_vop_tables(result, reference, moving):
            write_vops_csv(tmp / name, vops.xy, vops.z, to_file, vops.radius, vops.support, matched, unit_scale=scale)
        if result.details is not None and result.details.chosen is not None:
            try:
                from ..engine.report.figures import pair_figure

                pair_figure(result, tmp / "registration.png")
            except Exception as exc:  # a figure must never lose the result
                log.warning("could not draw the figure: %s", exc)
        if ok:
            write_text_atomic(tmp / "transform.txt", format_matrix(np.asarray(summary["matrix"])))
            if write_registered:
                to_units = np.diag([1.0 / scale, 1.0 / scale, 1.0 / scale, 1.0])
                write_scan(registered_points, tmp / f"{moving.name}_registered.laz", matrix=to_units @ result.matrix)
        write_text_atomic(tmp / "result.json", json.dumps(summary, indent=2) + "\n")
    reporter.done("", out / "result.json")
    if ok:
        icp = result.icp
        say(
            f"ok: {result.matched} matched VOPs ({result.reference_vops} / {result.moving_vops}), "
            f"ICP std {1000 * icp.std_m:.1f} mm, fitness {icp.fitness:.2f} -> {shown(out) / 'result.json'}",
            _ns(reporter),
        )
        if (out / "registration.png").exists():
            print(f"figure: {shown(out) / 'registration.png'}")
        return 0
    say(f"failed: {summary['reason']} -> {shown(out) / 'result.json'}", _ns(reporter), err=True)
    return 1


def _ns(reporter: Reporter) -> argparse.Namespace:
    return argparse.Namespace(reporter=reporter)


def check_near_scanner(scan, max_range_m: float, path, units: str) -> None:
    """Refuse, before the work, a scan with hardly any points within ``D_c`` of its scanner: a
    georeferenced scan without ``--scanner-position`` or a file in another unit than ``--units``."""
    from ..engine.core.errors import UsageError

    from ..engine.geometry.voxel import column_bounds
    from ..engine.tls.scanner_position import points_within

    lo, hi = column_bounds(scan.points)
    span = max(float(hi[0] - lo[0]), float(hi[1] - lo[1]))
    if span < 2.0:
        raise UsageError(
            f"{path}: with --units {units} the points span only {span:.2f} m horizontally; a forest scan spans tens of metres: "
            "check the file's unit (--units)")
    near = points_within(scan.points, scan.scanner_position, max_range_m)
    if near < 1000 or near < 0.01 * len(scan.points):
        pos = ", ".join(f"{v:.2f}" for v in scan.scanner_position_file / UNITS[units])
        raise UsageError(
            f"{path}: only {near} of {len(scan.points)} points lie within D_c = {max_range_m:g} m of the scanner position ({pos} {units}); "
            "for a georeferenced scan give --scanner-position X,Y,Z, and check the file's unit (--units cm|mm|ft)")
