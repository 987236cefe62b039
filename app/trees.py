"""Trees: detect and measure every tree (DBH, height, crown, stem curve, cylinder models) of a
ground-based, airborne or fused cloud (System B).

:func:`measure_trees_file` reads the cloud (moved first by a co-registration's transform when
given), measures (:func:`forestreg.engine.trees.inventory.measure_trees`) and writes the output
folder (``trees.csv``, ``stem_curves.csv``, ``cylinders/``, ``layers.gpkg``, ``report.html``, and
with field records ``evaluation/``) as one transaction. ``layers.gpkg`` holds the trees, their
crown outlines and the cloud's outline in the cloud's CRS (the co-registration's target CRS when
the cloud was moved by its transform; ``crs`` when the file declares none).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from .common import UNITS, RunOutcome, as_points, as_scan, check_units, check_upright, given_crs, params_of, with_cancel
from .units import tall_stand_note

log = logging.getLogger("forestreg")


@dataclass(frozen=True, eq=False)
class TreesOutcome(RunOutcome):
    """Measured trees: ``result`` is the engine's
    :class:`~forestreg.engine.trees.inventory.TreeInventory` (local frame, metres), ``points``
    the cloud measured (local frame), ``evaluation`` the outcome of the check against field
    records (or None), ``report`` the HTML report written (or None), ``crs`` the CRS of the
    outputs (:class:`~forestreg.engine.io.crs.FrameCrs`)."""

    method = "stems, segmentation, QSM"
    points: Any = None
    evaluation: Any = None
    report: Optional[Path] = None
    trees: int = 0
    crs: Any = None

    def evidence(self) -> dict:
        out = {"trees": self.trees, "method": getattr(self.result, "method", "")}
        stations = getattr(self.result, "stations", None)
        if stations is not None:
            out["scanner_stations"] = stations.describe()
        return out

    def line(self) -> str:
        return self.result.summary() if self.result is not None else f"{self.status}: {self.reason}"


def default_params():
    from ..engine.trees.inventory import TreeParams

    return TreeParams()


def measure_trees_in(cloud, params=None, *, progress=None, cancel=None):
    """The trees of ``cloud`` (a :class:`~forestreg.engine.core.scan.Scan`, local frame), no file
    written: the engine's :class:`~forestreg.engine.trees.inventory.TreeInventory`."""
    from ..engine.trees.inventory import measure_trees as measure

    return measure(
        cloud.points,
        params or default_params(),
        progress=with_cancel(progress, cancel),
        origin_shift=cloud.origin_shift,
    )


def measure_trees_file(
    cloud_path,
    out: Optional[str | Path],
    params=None,
    *,
    transform=None,
    field=None,
    units: str = "m",
    cylinders: bool = True,
    report: bool = True,
    crs=None,
    progress=None,
    cancel=None,
) -> TreesOutcome:
    """Measure the trees of ``cloud_path`` (a file, or a :class:`~forestreg.engine.core.scan.Scan`)
    into the folder ``out`` (a transaction; ``None``: nothing written); with ``field`` (field
    records CSV) the trees are also evaluated into ``out/evaluation``. ``transform`` (a
    co-registration's ``transform.txt``, files' unit) moves the cloud first. ``crs`` (e.g.
    "EPSG:32618") is the CRS of the outputs when the cloud's file (or, with ``transform``, the
    co-registration's ``result.json``) declares none, or the one that wins over it."""
    from ..engine.core.atomic import check_output_folder, output_folder
    from ..engine.core.transform import read_matrix, to_metres
    from ..engine.io import read_scan
    from ..engine.io.base import check_readable
    from ..engine.io.crs import crs_of, frame_crs
    from ..engine.trees.evaluate import read_tree_table
    from .evaluation import evaluate_into

    given = given_crs(crs, units)
    scale = UNITS[units]
    is_path = isinstance(cloud_path, (str, Path))
    if is_path:
        check_readable(cloud_path)
    if out is not None:
        out = check_output_folder(out, "trees", inputs=[cloud_path if is_path else None, transform, field])
    matrix = to_metres(read_matrix(transform), scale) if transform else None
    field_table = read_tree_table(field) if field else None  # checked before the work
    # the trees use x, y, z alone
    cloud = (
        read_scan(cloud_path, unit_scale=scale, with_intensity=False)
        if is_path
        else as_scan(cloud_path, "cloud", units=False)
    )
    check_units(
        cloud, units if is_path else "m", str(cloud_path) if is_path else cloud.name or "cloud"
    )  # before the work
    name = Path(cloud_path).name if is_path else cloud.name or "cloud"
    check_upright(cloud, str(cloud_path) if is_path else name)
    if matrix is not None:  # the moved cloud is in the co-registration's target frame
        frame = frame_crs(
            {"cloud": crs_of(cloud), "target": transform_target_crs(transform)},
            "target",
            given,
            names={"cloud": name, "target": f"the target of {Path(transform).name}"},
        )
        cloud = cloud.transformed(matrix)
    else:
        frame = frame_crs({"cloud": crs_of(cloud)}, "cloud", given, names={"cloud": name})
    params = params or default_params()
    if not cylinders:
        params = dataclasses.replace(params, cylinder_models=False)
    inventory = measure_trees_in(cloud, params, progress=progress, cancel=cancel)
    evaluation = None
    written = None
    if inventory and is_path and frame.crs is None:  # nothing says the file is in metres
        note = tall_stand_note([t.height_m for t in inventory.trees], units, name)
        if note:
            log.warning(note)
    if not inventory:  # the data do not allow trees: the reason, and no folder (complete or absent)
        return TreesOutcome(
            status="failed",
            reason=inventory.reason,
            timings=dict(inventory.timings),
            out=out,
            result=inventory,
            points=cloud.points,
            crs=frame,
        )
    if out is not None:
        from .layers import cloud_outline, trees_layers, write_layers

        with output_folder(out, "trees") as tmp:
            inventory.write(tmp, unit_scale=scale)
            write_layers(
                tmp,
                trees_layers(inventory, unit_scale=scale, outline=cloud_outline(cloud.points[:, :2]), cloud_name=name),
                frame.crs,
            )
            if report:
                from ..engine.report.trees_report import write_inventory_report

                write_inventory_report(tmp, inventory, cloud.points)
            written = (tmp / "report.html").exists()
            if field_table is not None:
                evaluation = evaluate_into(
                    tmp / "evaluation",
                    [("trees", read_tree_table(tmp / "trees.csv"))],
                    field_table,
                    by="position",
                    max_distance=1.0 / scale,
                    shown_as=out / "evaluation",
                )
    status, reason = "ok", ""
    if evaluation is not None and not evaluation:
        status, reason = "failed", evaluation.reason
    return TreesOutcome(
        status=status,
        reason=reason,
        timings=dict(inventory.timings),
        out=out,
        result=inventory,
        points=cloud.points,
        evaluation=evaluation,
        report=out / "report.html" if written else None,
        trees=len(inventory.trees),
        crs=frame,
    )


def transform_target_crs(transform):
    """The CRS of the frame a co-registration's transform maps into: the ``crs`` entry of its
    ``result.json`` (the file given, or the one beside ``transform.txt``); None when it names none."""
    import json

    from ..engine.io.crs import Crs

    if transform is None:
        return None
    p = Path(transform)
    result = p if p.suffix.lower() == ".json" else p.parent / "result.json"
    try:
        found = json.loads(result.read_text(encoding="utf-8")).get("crs")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return None
    return Crs.from_dict(found)


# ----------------------------------------------------------------------------- the Python API


def measure_trees(cloud, params=None, progress=None, *, origin_shift=None, single_tree=None, cancel=None):
    """Detect, segment and measure every tree of ``cloud``
    (:func:`forestreg.engine.trees.inventory.measure_trees`, same options; returns its
    :class:`~forestreg.engine.trees.inventory.TreeInventory`), checked as the ``trees`` command
    checks it, before any work.

    ``cloud``: a :class:`~forestreg.engine.core.scan.Scan`, an (N, 3) array of finite x, y, z in
    metres (z up; large georeferenced coordinates are shifted to a local origin and the rows keep
    them; with ``origin_shift`` the array is taken as local coordinates and the rows add it), or a
    point file's path (metres). Its coordinates must be in metres
    (:func:`~forestreg.app.common.check_units`: a cloud in cm or mm is refused at once with the
    likely unit). ``params``: a :class:`~forestreg.engine.trees.inventory.TreeParams` (or a
    :class:`~forestreg.engine.params.ProductParams`). Bad input raises the product's errors
    (:class:`~forestreg.engine.core.errors.ForestregError`); data that do not allow trees give a
    failed inventory with the reason."""
    import os

    import numpy as np

    from ..engine.core.scan import Scan
    from ..engine.trees.inventory import TreeParams
    from ..engine.trees.inventory import measure_trees as measure

    params = params_of(params, TreeParams, "trees")
    if origin_shift is not None and not isinstance(cloud, (Scan, str, os.PathLike)):
        shift = np.asarray(origin_shift, dtype=np.float64).reshape(-1)
        if shift.shape != (3,) or not np.isfinite(shift).all():
            from ..engine.core.errors import InvalidArgumentError

            raise InvalidArgumentError(f"origin_shift: expected three finite numbers, got {origin_shift!r}")
        scan = Scan.from_points(as_points(cloud, "cloud", min_points=10), origin_shift=np.zeros(3), name="cloud")
        check_units(scan, "m", "cloud")
    else:
        scan = as_scan(cloud, "cloud")
        shift = scan.origin_shift if origin_shift is None else np.asarray(origin_shift, dtype=np.float64)
    check_upright(scan, "cloud")
    return measure(scan.points, params, with_cancel(progress, cancel), origin_shift=shift, single_tree=single_tree)


def terrain_model(cloud, params=None, progress=None):
    """The ground mask and DEM of ``cloud`` (:func:`forestreg.engine.terrain.terrain_model`):
    a :class:`~forestreg.engine.core.scan.Scan` (its local frame), an (N, 3) array of finite x, y, z
    in metres or a point file's path, checked to be in metres; ``params`` a
    :class:`~forestreg.engine.terrain.TerrainParams`."""
    from ..engine.core.scan import Scan
    from ..engine.terrain import TerrainParams
    from ..engine.terrain import terrain_model as model

    if isinstance(cloud, (Scan, str)) or hasattr(cloud, "__fspath__"):
        points = as_scan(cloud, "cloud").points
    else:
        points = as_points(cloud, "cloud", min_points=10)
        check_units(points, "m", "cloud")
    return model(points, params_of(params, TerrainParams, ""), progress)


def read_trees_folder(folder):
    """A ``forestreg trees`` output folder (:class:`~forestreg.engine.io.results.TreesOutput`),
    its cylinder files read as cylinder models (:class:`~forestreg.engine.trees.qsm.CylinderModel`)."""
    from ..engine.io.results import read_trees_dir
    from ..engine.trees.qsm import CylinderModel

    return read_trees_dir(folder, cylinder_model=CylinderModel)


# ----------------------------------------------------------------------------- edits


def edit(kind: str, trees=(), **where):
    """A :class:`~forestreg.engine.trees.edit.TreeEdit`: "delete", "merge", "split", "add",
    "dbh_height" of the trees ``trees`` (``xy`` local coordinates, ``height_m``)."""
    from ..engine.trees.edit import TreeEdit

    return TreeEdit(kind, tuple(trees), **where)


def apply_tree_edit(points, inventory, change, params=None):
    """The inventory after ``change`` (only its trees measured again)."""
    from ..engine.trees.edit import apply_edit

    return apply_edit(points, inventory, change, params or default_params())


def edit_notes(base, steps) -> dict:
    """Tree id -> the note of each tree changed by the edits ``steps`` ([(edit, inventory), ...])."""
    from ..engine.trees.edit import edit_notes as notes

    return notes(base, steps)


def save_edited(folder, inventory, notes, edits, points=None, *, report: bool = True) -> Path:
    """Write the edited inventory like ``forestreg trees`` (with the points: also the report),
    then add an ``edited`` column to ``trees.csv`` (the notes of each tree's edits, "" for the
    others) and the edits as ``edits.json`` with the content hash of the cloud they were made on
    (replayable on that cloud with :func:`~forestreg.engine.trees.edit.apply_edits`); ``layers.gpkg``
    is written again from the edited trees, in the CRS of the one the folder held (local without
    one). Returns the trees.csv path."""
    import numpy as np

    from ..engine.io.gpkg import read_crs as layers_crs
    from ..engine.io.results import write_edits
    from ..engine.trees.edit import cloud_digest
    from .layers import LAYERS_FILE, cloud_outline, trees_layers, write_layers

    crs = layers_crs(Path(folder) / LAYERS_FILE)
    path = inventory.write(folder)
    write_layers(
        folder,
        trees_layers(inventory, outline=None if points is None else cloud_outline(np.asarray(points)[:, :2])),
        crs,
    )
    if report and points is not None:
        from ..engine.report.trees_report import write_inventory_report

        write_inventory_report(folder, inventory, points)
    cloud = None if points is None else {"points": int(len(points)), "sha256": cloud_digest(points)}
    write_edits(path, notes, [e.to_dict() for e in edits], cloud)
    return path
