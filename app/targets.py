"""Targets: reflector targets (bright small discs or cylinders) detected in scans with intensity,
named after known targets when given, written as a targets CSV (``forestreg targets``); the
manual (target-based) registration of a plot reads them back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

from .common import RunOutcome, refuse_scans_given_twice, with_cancel


@dataclass(frozen=True)
class ScanTargets:
    """The reflectors of one scan: how many were detected, and how many named after known ones
    (None without known targets for that scan)."""

    name: str
    detected: int
    named: Optional[int] = None


@dataclass(frozen=True, eq=False)
class TargetsOutcome(RunOutcome):
    """The targets CSV written to ``out``, with ``scans`` (:class:`ScanTargets`, in input order)."""

    method = "intensity reflectors"
    scans: tuple = ()
    found: dict = field(default_factory=dict)


def detect_targets(
    scans: Sequence, out, *, known: Optional[str] = None, max_distance: float = 0.3, progress=None, cancel=None
) -> TargetsOutcome:
    """Detect the reflectors of each scan file and write the targets CSV ``out`` (scan, target,
    x, y, z; a new file: never an input, never an existing table, which may hold targets picked
    by hand). With ``known`` (an approximate targets CSV) each detection within ``max_distance``
    metres is named after the nearest known target."""
    from ..engine.core.atomic import check_output_file
    from ..engine.core.errors import OutputPathError
    from ..engine.io import read_scan
    from ..engine.io.base import check_readable
    from ..engine.io.results import write_targets_csv
    from ..engine.tls.manual import detect_reflectors, match_detected_to_known, read_targets_csv

    for p in scans:
        check_readable(p)
    refuse_scans_given_twice(scans)
    out = check_output_file(out, inputs=list(scans) + ([known] if known else []), suffixes=(".csv", ".txt"))
    if Path(out).exists():
        raise OutputPathError(
            f"{out} exists: a targets table is never replaced (it may hold targets picked by hand); give a new file name"
        )
    known_targets = read_targets_csv(known) if known else {}
    step = with_cancel(progress, cancel) or (lambda f, m: None)
    found: dict = {}
    rows = []
    for k, path in enumerate(scans):
        step(k / len(scans), f"detecting reflectors in {Path(path).name}")
        scan = read_scan(path)
        detected = detect_reflectors(scan)
        name = Path(path).name
        if name in known_targets:
            found[name] = match_detected_to_known(detected, known_targets[name], max_distance)
        else:
            found[name] = {f"R{j + 1}": d.centre for j, d in enumerate(detected)}
        rows.append(ScanTargets(name, len(detected), len(found[name]) if name in known_targets else None))
    write_targets_csv(out, found)
    return TargetsOutcome(status="ok", out=out, scans=tuple(rows), found=found)


def read_targets(path) -> dict:
    """A targets CSV (scan, target, x, y, z): scan name -> target id -> position."""
    from ..engine.tls.manual import read_targets_csv

    return read_targets_csv(path)


def write_targets(path, targets_by_scan) -> None:
    """Write every scan's targets as a targets CSV (atomically)."""
    from ..engine.io.results import write_targets_csv

    write_targets_csv(path, targets_by_scan)


def reflectors_in(scan, known: Optional[dict] = None, max_distance_m: float = 0.5):
    """The reflectors detected in ``scan`` and, with ``known`` targets, the detections named after
    them (within ``max_distance_m``): ``(detected, named)``."""
    from ..engine.tls.manual import detect_reflectors, match_detected_to_known

    found = detect_reflectors(scan)
    named = match_detected_to_known(found, known, max_distance_m) if known else {}
    return found, named
