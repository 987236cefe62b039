"""Pair registration: a moving TLS scan onto a reference scan from trunk shadows (System A).

:func:`register_pair` reads both scans, locates and checks their scanners, registers
(:func:`forestreg.engine.tls.pair.register`), applies the last rigid check, converts the matrices
into the files' unit and writes the output folder (``result.json``, ``transform.txt``, the VOP
tables, the figure, optionally the registered scan) as one transaction. The outputs are in the
reference scan's frame and take its CRS (``result.json``'s ``crs``; the registered scan's WKT VLR).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .common import (
    UNITS,
    RunOutcome,
    as_scan,
    check_near_scanner,
    check_units,
    given_crs,
    import_in_background,
    outcome_of,
    params_of,
    refuse_same_file,
    run_summary,
    scan_source,
    with_cancel,
)

log = logging.getLogger("forestreg")


@dataclass(frozen=True, eq=False)
class PairOutcome(RunOutcome):
    """A registered (or failed) pair: ``result`` is the engine's
    :class:`~forestreg.engine.tls.pair.PairResult` (metres); ``matrix`` and ``summary`` are in the
    files' unit; ``figure`` is the figure written (or None)."""

    method = "auto (trunk shadows + ICP)"
    convention = "p_reference = matrix @ p_moving (files' coordinates)"
    figure: Optional[Path] = None


def register_pair(
    reference_path: str | Path,
    moving_path: str | Path,
    out: Optional[str | Path],
    params=None,
    *,
    positions: Sequence = (),
    ups: Sequence = (),
    units: str = "m",
    write_registered: bool = False,
    scanner_params=None,
    crs=None,
    progress=None,
    cancel=None,
) -> PairOutcome:
    """Register ``moving_path`` onto ``reference_path``; with ``out``, write that output folder as
    a transaction (``None``: nothing written). ``positions`` (0-2 scanner positions in file
    coordinates) and ``ups`` (0-2 vertical directions) are for the reference, then the moving scan.
    Raises on bad input (:class:`~forestreg.engine.core.errors.UsageError`, ...); a pair the data
    do not allow comes back as a failed outcome with the reason. ``scanner_params``: the
    :class:`~forestreg.engine.tls.params.ScannerPositionParams` of a scan whose file does not
    say where its scanner stood. ``crs`` (e.g. "EPSG:32618"): the CRS of the reference frame when
    its file declares none, or the one that wins over it."""
    from concurrent.futures import ThreadPoolExecutor

    given = given_crs(crs, units)
    from ..engine.core.atomic import check_output_folder
    from ..engine.core.errors import UsageError
    from ..engine.io import read_scan
    from ..engine.tls.params import RegistrationParams

    params = params or RegistrationParams()
    if len(positions) > 2:
        raise UsageError("--scanner-position is given at most twice (reference, then moving)")
    if len(ups) > 2:
        raise UsageError("--up is given at most twice (reference, then moving)")
    refuse_same_file(
        reference_path, moving_path, "REFERENCE and MOVING are the same file: a scan cannot be registered onto itself"
    )
    scale = UNITS[units]
    if out is not None:
        out = check_output_folder(out, "register", inputs=[reference_path, moving_path])
    progress = with_cancel(progress, cancel)

    def read(path, index: int):
        # the registration uses the coordinates alone: intensity only for the registered scan written
        scan = read_scan(
            path,
            scanner_position=positions[index] if len(positions) > index else None,
            unit_scale=scale,
            with_intensity=write_registered and index == 1,
        )
        check_units(scan, units, str(path))  # before the scanner is looked for: a file in cm is refused at once
        return scan

    # both scans are read, one after the other (the decompression is multi-core), while the
    # registration engine is imported
    early = ThreadPoolExecutor(1, thread_name_prefix="forestreg-read")
    pending = {
        0: early.submit(read, reference_path, 0),
        1: early.submit(read, moving_path, 1),
    }  # popped when used: the scan's points are not held
    early.shutdown(wait=False)
    if out is not None:
        import_in_background(".engine.report.figures", kernels="pair")
    from ..engine.tls.pair import register as register_scans
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
            scan = locate_scanner(scan, scanner_params)
            check_near_scanner(scan, params.max_range_m, path, units, units_checked=True)
            kept[role] = scan.without_points()
            if role == "moving" and write_registered:
                kept["registered_points"] = scan
            return scan

        return load

    ups = [None if u is None else np.asarray(u, dtype=float) for u in ups]
    result = register_scans(
        reader(reference_path, 0, "reference"),
        reader(moving_path, 1, "moving"),
        params,
        progress=progress,
        reference_up=ups[0] if len(ups) > 0 else None,
        moving_up=ups[1] if len(ups) > 1 else None,
    )
    read_s = sum(result.timings.get(f"read_{role}_s", 0.0) for role in ("reference", "moving"))
    summary, ok = run_summary(
        result,
        {"read_s": read_s},
        {"reference_file": reference_path, "moving_file": moving_path},
        units,
        scale,
        matrix_keys=("matrix", "coarse_matrix"),
    )
    frame = _frame_crs(kept, reference_path, moving_path, given)
    kept["crs"] = frame.crs
    frames = {
        "transform.txt": f"maps {frame.label_of('moving')} onto {frame.label_of('reference')}",
        "reference_vops.csv": frame.label_of("reference"),
        "moving_vops.csv": frame.label_of("moving"),
    }
    if write_registered:
        stem = getattr(kept.get("moving"), "name", "") or Path(moving_path).stem
        frames[f"{stem}_registered.laz"] = (
            f"the reference frame ({frame.crs.label if frame.crs is not None else 'no CRS'})"
        )
    summary["crs"] = frame.to_dict(frames=frames)
    figure = None
    if out is not None:
        figure = _write_pair_folder(out, result, summary, kept, scale, write_registered)
        from ..engine.core.jit import remember_loaded

        remember_loaded("pair")  # the kernels the next pair loads while its files are read
    return outcome_of(summary, out=out, result=result, cls=PairOutcome, figure=figure)


def _frame_crs(kept: dict, reference_path, moving_path, given):
    """The CRS of a pair's outputs: the reference scan's (or ``given``), and each scan's."""
    from ..engine.io.crs import crs_of, frame_crs

    return frame_crs(
        {"reference": crs_of(kept.get("reference")), "moving": crs_of(kept.get("moving"))},
        "reference",
        given,
        names={"reference": Path(reference_path).name, "moving": Path(moving_path).name},
    )


# ----------------------------------------------------------------------------- the Python API


def register(reference, moving, params=None, *, scanner_params=None, **options):
    """Register ``moving`` onto ``reference`` (:func:`forestreg.engine.tls.pair.register`, same
    options; returns its :class:`~forestreg.engine.tls.pair.PairResult`), the scans checked as the
    ``register`` command checks them, before any work.

    Each scan is a :class:`~forestreg.engine.core.scan.Scan`, an (N, 3) array of x, y, z in metres
    (its scanner at the origin), a point file's path (metres), or a function without arguments
    that reads one. Its coordinates must be in metres
    (:func:`~forestreg.app.common.check_units`), its scanner is located
    (:func:`~forestreg.engine.tls.scanner_position.locate_scanner`) and must have points near it.
    ``params``: a :class:`~forestreg.engine.tls.params.RegistrationParams` (or a
    :class:`~forestreg.engine.params.ProductParams`). Bad input raises the product's errors
    (:class:`~forestreg.engine.core.errors.ForestregError`: another type, not (N, 3), NaN, wrong
    unit, no points near the scanner); a pair the data do not allow comes back failed with the
    reason."""
    from ..engine.core.errors import UsageError
    from ..engine.tls.pair import register as register_scans
    from ..engine.tls.params import RegistrationParams, ScannerPositionParams
    from ..engine.tls.scanner_position import locate_scanner

    params = params_of(params, RegistrationParams, "registration")
    scanner_params = params_of(scanner_params, ScannerPositionParams, "scanner_position")
    if reference is moving:
        raise UsageError("reference and moving are the same scan: a scan cannot be registered onto itself")

    def checked(source, role: str):
        source = scan_source(source, role)

        def load():
            scan = locate_scanner(source() if callable(source) else source, scanner_params)
            check_near_scanner(scan, params.max_range_m, role, "m", units_checked=True)
            return scan

        return load

    from .common import rigid_or_withheld

    return rigid_or_withheld(
        register_scans(
            checked(reference, "reference"), checked(moving, "moving"), params, scanner_params=scanner_params, **options
        )
    )


def register_manual(reference, moving, reference_targets, moving_targets, params=None, **options):
    """Register ``moving`` onto ``reference`` from shared targets
    (:func:`forestreg.engine.tls.manual.register_manual`, same arguments), each scan a
    :class:`~forestreg.engine.core.scan.Scan`, an (N, 3) array of x, y, z in metres or a point
    file's path, checked to be in metres; ``params`` a
    :class:`~forestreg.engine.tls.params.RegistrationParams`."""
    from ..engine.tls.manual import register_manual as register_targets
    from ..engine.tls.params import RegistrationParams

    return register_targets(
        as_scan(reference, "reference"),
        as_scan(moving, "moving"),
        reference_targets,
        moving_targets,
        params_of(params, RegistrationParams, "registration"),
        **options,
    )


def locate_scanner(scan, params=None):
    """The scan with a trustworthy scanner position
    (:func:`forestreg.engine.tls.scanner_position.locate_scanner`): ``scan`` a
    :class:`~forestreg.engine.core.scan.Scan`, an (N, 3) array of x, y, z in metres or a point
    file's path, checked to be in metres; ``params`` a
    :class:`~forestreg.engine.tls.params.ScannerPositionParams`."""
    from ..engine.tls.params import ScannerPositionParams
    from ..engine.tls.scanner_position import locate_scanner as locate

    return locate(as_scan(scan, "scan"), params_of(params, ScannerPositionParams, "scanner_position"))


def _write_pair_folder(
    out: Path, result, summary: dict, kept: dict, scale: float, write_registered: bool
) -> Optional[Path]:
    """The output folder of a pair, as one transaction (:func:`~forestreg.app.outputs.write_result_folder`):
    the VOP tables, the figure, the registered scan when asked and "ok"; returns the figure's path
    (or None)."""
    from ..engine.io import write_scan
    from ..engine.io.tables import pair_vop_tables, write_vops_csv
    from .outputs import write_result_folder

    reference, moving = kept["reference"], kept["moving"]

    def write_files(tmp: Path) -> None:
        for scan, to_file, vops, matched, name in pair_vop_tables(result, reference, moving):
            write_vops_csv(tmp / name, vops.xy, vops.z, to_file, vops.radius, vops.support, matched, unit_scale=scale)
        if summary["status"] == "ok" and write_registered:
            to_units = np.diag([1.0 / scale, 1.0 / scale, 1.0 / scale, 1.0])
            write_scan(
                kept["registered_points"],
                tmp / f"{moving.name}_registered.laz",
                matrix=to_units @ result.matrix,
                crs=kept.get("crs"),
            )

    def draw(tmp: Path) -> None:
        from ..engine.report.figures import pair_figure

        pair_figure(result, tmp / "registration.png")

    chosen = result.details is not None and result.details.chosen is not None
    return write_result_folder(
        out, "register", summary, write_files, draw=draw if chosen else None, drawn_name="registration.png"
    )
