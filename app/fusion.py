"""Fusion: co-registered ground-based and UAV clouds into one cloud, duplicates and noise removed
(System B).

:func:`fuse_clouds` checks the inputs and the output file before the work, reads the clouds, fuses
them (:func:`forestreg.engine.coreg.fusion.fuse_files`) and writes the fused LAS/LAZ atomically.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from .common import UNITS, RunOutcome, check_replaceable_point_file, with_cancel


@dataclass(frozen=True)
class SourceCounts:
    """Points of one source ("ground", "uav" or "total") through the fusion: read in, removed as
    duplicates of the other cloud, removed as noise, and kept."""

    input: int
    redundant: int
    noise: int
    kept: int

    @classmethod
    def of(cls, d) -> "SourceCounts":
        return cls(*(int(d.get(k) or 0) for k in ("input", "redundant", "noise", "kept")))

    def line(self, source: str) -> str:
        """``ground: 1,000 in, 10 redundant, 5 noise, 985 kept``."""
        return f"{source}: {self.input:,} in, {self.redundant:,} redundant, {self.noise:,} noise, {self.kept:,} kept"


@dataclass(frozen=True, eq=False)
class FusionOutcome(RunOutcome):
    """The fused cloud written to ``out``: ``counts`` per source ("ground", "uav", "total": input,
    redundant, noise, kept), ``points`` kept; ``result`` is the engine's
    :class:`~forestreg.engine.coreg.fusion.FusionResult`."""

    method = "redundancy + statistical noise removal"
    convention = "points in the UAV cloud's frame"
    counts: dict = field(default_factory=dict)
    points: int = 0

    def evidence(self) -> dict:
        return {"counts": self.counts, "points": self.points}

    @property
    def sources(self) -> dict[str, SourceCounts]:
        """The counts per source, typed ("ground", "uav", "total")."""
        return {source: SourceCounts.of(c) for source, c in self.counts.items()}


def default_params():
    from ..engine.coreg.fusion import FusionParams

    return FusionParams()


def fuse_clouds(
    ground_path: str | Path, uav_path: str | Path, out: str | Path, params=None, *,
    matrix: Optional[np.ndarray] = None, transform: Optional[str | Path] = None, units: str = "m",
    progress=None, cancel=None,
) -> FusionOutcome:
    """Fuse ``ground_path`` into ``uav_path``'s frame and write the LAS/LAZ ``out`` (refused when
    it is an input or a user's own cloud). The ground-to-UAV transform is ``matrix`` (metres, file
    coordinates) or read from ``transform`` (``transform.txt`` or ``result.json`` of a
    co-registration, in the files' unit); identity when neither is given."""
    from ..engine.core.atomic import check_output_file
    from ..engine.core.transform import read_matrix, to_metres
    from ..engine.coreg.fusion import fuse_files
    from ..engine.io import write_fused
    from ..engine.io.base import check_readable

    scale = UNITS[units]
    check_readable(ground_path)
    check_readable(uav_path)
    out = check_output_file(out, inputs=[ground_path, uav_path, transform], suffixes=(".laz", ".las"))
    check_replaceable_point_file(out, "source", "fused cloud")
    if matrix is None:
        matrix = to_metres(read_matrix(transform), scale) if transform else np.eye(4)
    params = params or default_params()
    # the ground-based cloud is read inside, and let go once merged: a scan's points less to hold
    result, shift = fuse_files(ground_path, uav_path, matrix, params, unit_scale=scale, progress=with_cancel(progress, cancel))
    write_fused(out, result, origin_shift=shift, unit_scale=scale)
    counts = {k: dict(v) for k, v in result.counts.items()}
    return FusionOutcome(status="ok", timings=dict(result.seconds), out=out, summary=result.summary(), result=result,
                         counts=counts, points=len(result.points))
