"""Fusion: co-registered ground-based and UAV clouds into one cloud, duplicates and noise removed
(System B).

:func:`fuse_clouds` checks the inputs and the output file before the work, reads the clouds, fuses
them (:func:`forestreg.engine.coreg.fusion.fuse_files`) and writes the fused LAS/LAZ atomically, in
the UAV cloud's frame and with its CRS (a WKT VLR): clouds whose files declare two different CRSs
are refused unless ``crs`` says which one the output is in.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .common import (
    UNITS,
    RunOutcome,
    as_points,
    as_scan,
    check_replaceable_point_file,
    check_units,
    given_crs,
    params_of,
    refuse_same_file,
    with_cancel,
)
from .units import unit_of_scale


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
    :class:`~forestreg.engine.coreg.fusion.FusionResult`; ``crs`` the fused cloud's CRS and each
    input's (:class:`~forestreg.engine.io.crs.FrameCrs`)."""

    method = "redundancy + statistical noise removal"
    convention = "points in the UAV cloud's frame"
    counts: dict = field(default_factory=dict)
    points: int = 0
    crs: Any = None

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
    ground_path: str | Path,
    uav_path: str | Path,
    out: str | Path,
    params=None,
    *,
    matrix: Optional[np.ndarray] = None,
    transform: Optional[str | Path] = None,
    units: str = "m",
    crs=None,
    progress=None,
    cancel=None,
) -> FusionOutcome:
    """Fuse ``ground_path`` into ``uav_path``'s frame and write the LAS/LAZ ``out`` (refused when
    it is an input or a user's own cloud). The ground-to-UAV transform is ``matrix`` (metres, file
    coordinates) or read from ``transform`` (``transform.txt`` or ``result.json`` of a
    co-registration, in the files' unit); identity when neither is given. The fused cloud has the
    UAV cloud's CRS, or ``crs`` (e.g. "EPSG:32618") when given; two files declaring different CRSs
    without ``crs`` are refused (:class:`~forestreg.engine.core.errors.UsageError`, exit 2)."""
    from ..engine.core.atomic import check_output_file
    from ..engine.core.transform import read_matrix, to_metres
    from ..engine.coreg.fusion import fuse_files as fuse_point_files
    from ..engine.io import read_crs, write_fused
    from ..engine.io.base import check_readable
    from ..engine.io.crs import frame_crs

    given = given_crs(crs, units)
    scale = UNITS[units]
    check_readable(ground_path)
    check_readable(uav_path)
    refuse_same_file(ground_path, uav_path, "GROUND and UAV are the same file: a cloud is not fused with itself")
    frame = frame_crs(
        {"ground": read_crs(ground_path), "uav": read_crs(uav_path)},
        "uav",
        given,
        names={"ground": Path(ground_path).name, "uav": Path(uav_path).name},
        refuse_mixed="fuse",
    )
    out = check_output_file(out, inputs=[ground_path, uav_path, transform], suffixes=(".laz", ".las"))
    check_replaceable_point_file(out, "source", "fused cloud")
    if matrix is None:
        matrix = to_metres(read_matrix(transform), scale) if transform else np.eye(4)
    params = params or default_params()
    check_file_units((uav_path, ground_path), units)
    # the ground-based cloud is read inside, and let go once merged: a scan's points less to hold
    result, shift = fuse_point_files(
        ground_path, uav_path, matrix, params, unit_scale=scale, progress=with_cancel(progress, cancel)
    )
    write_fused(out, result, origin_shift=shift, unit_scale=scale, crs=frame.crs)
    counts = {k: dict(v) for k, v in result.counts.items()}
    summary = {**result.summary(), "crs": frame.to_dict()}
    return FusionOutcome(
        status="ok",
        timings=dict(result.seconds),
        out=out,
        summary=summary,
        result=result,
        counts=counts,
        points=len(result.points),
        crs=frame,
    )


def check_file_units(paths, units: str = "m", *, scale: Optional[float] = None) -> None:
    """Before a fusion: each file's coordinates are in ``units`` (``scale`` metres per unit when
    it is none of the ``--units`` choices) (:func:`~forestreg.app.common.check_units`). Each file is read once for this and let go (the
    fusion reads them again as it needs them, so its peak memory stays one scan's points less than
    holding both: reading costs a few per cent of a fusion's time)."""
    from ..engine.io import read_scan

    for path in paths:
        scan = read_scan(path, unit_scale=UNITS[units] if scale is None else scale, with_intensity=False)
        check_units(scan, units, str(path))
        del scan


# ----------------------------------------------------------------------------- the Python API


def fuse(ground_points, uav_points, params=None, *, ground_extra=None, uav_extra=None, progress=None):
    """Fuse co-registered ground-based and UAV points (:func:`forestreg.engine.coreg.fusion.fuse`,
    same options; returns its :class:`~forestreg.engine.coreg.fusion.FusionResult`): each an (N, 3)
    array of finite x, y, z in metres, in one frame (or a :class:`~forestreg.engine.core.scan.Scan`:
    its local points), one of them may be empty; each checked to be in metres
    (:func:`~forestreg.app.common.check_units`). ``params``: a
    :class:`~forestreg.engine.coreg.fusion.FusionParams` (or a
    :class:`~forestreg.engine.params.ProductParams`)."""
    from ..engine.coreg.fusion import FusionParams
    from ..engine.coreg.fusion import fuse as fuse_points

    clouds = []
    for points, what in ((ground_points, "ground-based points"), (uav_points, "UAV points")):
        p = as_points(points, what, min_points=0)
        if len(p):
            check_units(p, "m", what)
        clouds.append(p)
    return fuse_points(
        clouds[0],
        clouds[1],
        params_of(params, FusionParams, "fusion"),
        ground_extra=ground_extra,
        uav_extra=uav_extra,
        progress=progress,
    )


def fuse_scans(ground, uav, matrix, params=None, *, progress=None):
    """Fuse a ground-based scan into a UAV scan's frame (:func:`forestreg.engine.coreg.fusion.fuse_scans`;
    ``p_uav = matrix @ p_ground`` in file coordinates, metres): each a
    :class:`~forestreg.engine.core.scan.Scan`, an (N, 3) array of finite x, y, z in metres or a
    point file's path, checked to be in metres; ``matrix`` a rigid 4x4
    (:func:`~forestreg.engine.core.transform.check_rigid`)."""
    from ..engine.core.transform import check_rigid
    from ..engine.coreg.fusion import FusionParams
    from ..engine.coreg.fusion import fuse_scans as fuse_two

    m = check_rigid(matrix, "matrix")
    return fuse_two(
        as_scan(ground, "ground"), as_scan(uav, "uav"), m, params_of(params, FusionParams, "fusion"), progress=progress
    )


def fuse_files(ground_path, uav_path, matrix, params=None, *, unit_scale: float = 1.0, progress=None):
    """:func:`forestreg.engine.coreg.fusion.fuse_files` (same arguments: the result and the UAV
    scan's origin shift) of two point files, each checked first to be in metres once
    ``unit_scale`` is applied (:func:`~forestreg.app.common.check_units`); ``matrix`` a rigid 4x4
    in metres."""
    import os

    from ..engine.core.errors import InvalidArgumentError
    from ..engine.core.transform import check_rigid
    from ..engine.coreg.fusion import FusionParams
    from ..engine.coreg.fusion import fuse_files as fuse_point_files
    from ..engine.io.base import check_readable, check_unit_scale

    for path, what in ((ground_path, "ground_path"), (uav_path, "uav_path")):
        if not isinstance(path, (str, os.PathLike)):
            raise InvalidArgumentError(
                f"{what}: expected the path of a point file (str or pathlib.Path), got {type(path).__name__}"
            )
        check_readable(path)
    m = check_rigid(matrix, "matrix")
    scale = check_unit_scale(unit_scale)
    params = params_of(params, FusionParams, "fusion")
    check_file_units((uav_path, ground_path), unit_of_scale(scale), scale=scale)
    return fuse_point_files(ground_path, uav_path, m, params, unit_scale=scale, progress=progress)
