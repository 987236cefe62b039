"""Change: two surveys of one plot years apart, registered on what persisted, compared tree by tree.

:func:`detect_change_files` reads BEFORE and AFTER (each a merged ground-based cloud in any frame,
a saved plot project, or a ``trees.csv`` / folder of ``forestreg trees``), measures the trees of
each cloud, registers AFTER onto BEFORE from the persisting stems and the terrain
(:func:`forestreg.engine.change.detect_change`), checks the result (a rigid matrix, the files'
unit) and writes the output folder as one transaction:

- ``result.json``: status, reason, ``matrix`` (``p_before = matrix @ p_after``, file coordinates,
  the files' unit), ``convention``, evidence, ``uncertainty`` {``translation_m``,
  ``rotation_deg``} (1 sigma), the tree counts, the inputs, ``crs`` (BEFORE's frame: its CRS and
  each survey's);
- ``tree_changes.csv``: one row per tree (status, x, y in BEFORE file coordinates, DBH and height
  in each survey and their changes in metres, flag, ids and 1-sigma values);
- ``layers.gpkg``: the same trees as points (``tree_changes``) and their outline, in BEFORE's CRS;
- ``report.html``: the change map and the figures.

A registration that the data do not allow (unrelated plots, too few persisting stems, an
ambiguous heading) gives an outcome "failed" with the reason, and a folder with ``result.json``
and ``report.html`` only.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Optional

import numpy as np

from .common import (
    UNITS,
    RunOutcome,
    check_units,
    check_upright,
    given_crs,
    outcome_of,
    refuse_same_file,
    run_summary,
    with_cancel,
)

__all__ = ["ChangeOutcome", "ChangeSummary", "change_rows", "detect_change_files", "read_change_folder", "read_epoch"]


@dataclass(frozen=True, eq=False)
class ChangeOutcome(RunOutcome):
    """The outcome of ``change``: ``status``, ``reason``, ``matrix`` (4x4, file coordinates in the
    files' unit, or None), ``timings``, ``out`` (the folder written, or None), ``summary`` (the
    ``result.json``), ``result`` (the engine's :class:`~forestreg.engine.change.ChangeResult`),
    ``rows`` (the ``tree_changes.csv`` rows), ``notes`` (what reading the inputs did that a user
    should know: a DBH column converted, rows left out). Falsy when not ok."""

    rows: list = field(default_factory=list)
    notes: tuple = ()

    method: ClassVar[str] = "re-survey (persisting stems from any heading + ICP on stem slices and terrain)"
    convention: ClassVar[str] = "p_before = matrix @ p_after (file coordinates of BEFORE and AFTER)"

    def line(self) -> str:
        """One line for a terminal."""
        return self.result.summary() if self.result is not None else f"{self.status}: {self.reason}"


@dataclass(frozen=True)
class ChangeSummary:
    """A re-survey's ``result.json``, typed: ``status``, ``reason``, the persisting stems the
    registration used, the trees per status (persisting, removed, new, outside the other survey)
    and the registration's 1-sigma uncertainty (position at the scanner, m; rotation, degrees;
    None where unknown)."""

    status: str
    reason: str = ""
    persisting_stems: Optional[int] = None
    persisting: int = 0
    removed: int = 0
    new: int = 0
    outside: int = 0
    translation_m: Optional[float] = None
    rotation_deg: Optional[float] = None

    @classmethod
    def of(cls, d) -> "ChangeSummary":
        from ..engine.core.outcome import OutcomeRecord
        from .saved import count_or_none, finite_or_none, mapping_or_empty

        rec = OutcomeRecord.from_dict(d)
        trees, unc = mapping_or_empty(rec.get("trees")), mapping_or_empty(rec.get("uncertainty"))
        return cls(
            rec.status,
            rec.reason,
            count_or_none(rec.evidence.get("persisting_stems")),
            *(count_or_none(trees.get(k)) or 0 for k in ("persisting", "removed", "new", "outside")),
            finite_or_none(unc.get("translation_m")),
            finite_or_none(unc.get("rotation_deg")),
        )

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def trees(self) -> int:
        """Trees in the table (every status)."""
        return self.persisting + self.removed + self.new + self.outside


#: What a change table can be filtered by: every tree, the flagged ones, or one status.
ROW_FILTERS = ("all trees", "persisting", "removed", "new", "outside", "flagged")


def change_rows(rows, shown: str = "all trees") -> list:
    """The rows of ``tree_changes.csv`` (as :func:`~forestreg.engine.io.change.read_change_dir`
    reads them) that ``shown`` (one of :data:`ROW_FILTERS`) selects."""
    if shown == "all trees":
        return list(rows)
    if shown == "flagged":
        return [r for r in rows if r.get("flag")]
    return [r for r in rows if r.get("status") == shown]


def read_change_folder(folder):
    """A ``forestreg change --out DIR`` folder (:class:`~forestreg.engine.io.change.ChangeOutput`)
    and its typed :class:`ChangeSummary`."""
    from ..engine.io.change import read_change_dir

    out = read_change_dir(folder)
    return out, ChangeSummary.of(out.result)


def _input_kind(path: Path) -> str:
    """ "table" (a table of trees, :func:`~forestreg.engine.io.sniff.is_tree_table`, or a folder
    holding a ``trees.csv``), "project" (a plot project file) or "cloud"; a missing or unreadable
    input is a one-line error."""
    from ..engine.core.errors import UsageError
    from ..engine.io.base import check_readable
    from ..engine.io.las import check_las_header
    from ..engine.io.sniff import detect_format, is_tree_table

    if path.is_dir():
        if (path / "trees.csv").is_file():
            return "table"
        raise UsageError(
            f"{path} is a folder without trees.csv: give a cloud, a project file or the trees.csv of 'forestreg trees'"
        )
    check_readable(path)
    if path.suffix.lower() == ".json":
        return "project"
    if is_tree_table(path):
        return "table"
    if detect_format(path) == "las":  # a damaged or truncated header is known before any work
        check_las_header(path)
    return "cloud"


def _real_input(path: Path) -> Path:
    """The file an input stands for: a folder's ``trees.csv``, links and ``..`` resolved."""
    return ((path / "trees.csv") if path.is_dir() else path).resolve()


def _read_table(path: Path, role: str, scale: float, change_params):
    """The trees of a table (a ``trees.csv`` or a folder holding one) and what reading it did."""
    from ..engine.change import epoch_from_table
    from ..engine.io.tables import read_trees_table

    table = read_trees_table(path / "trees.csv" if path.is_dir() else path)
    epoch = epoch_from_table(
        table.rows,
        name=f"{role} ({table.path.name})",
        unit_scale=scale,
        change=change_params,
        lines=table.lines,
        dbh_column=table.dbh_column,
    )
    return epoch, table.notes + epoch.notes


def _project_cloud(path: Path, scale: float):
    """The cloud of a saved plot project (local frame, metres) and where it came from: its
    trees folder's ``trees.csv`` when it has one (returned as a path), else its ground-based or
    fused cloud, else its registered scans merged in the project frame."""
    from ..engine.core.errors import UsageError
    from ..engine.core.scan import Scan
    from ..engine.core.transform import apply, to_metres
    from ..engine.io import read_scan
    from ..engine.tls.project import Project

    project = Project.load(path)
    for name in ("ground", "fused", *project.forest.trees):
        folder = project.forest.trees.get(name)
        if folder is not None and (Path(folder) / "trees.csv").is_file():
            return Path(folder) / "trees.csv", f"trees of project {path.name} ({name})"
    for cloud in (project.forest.ground_cloud, project.forest.fused_cloud):
        if cloud is not None and Path(cloud).is_file():
            return read_scan(
                cloud, unit_scale=scale, with_intensity=False
            ), f"cloud of project {path.name} ({Path(cloud).name})"
    poses = project.poses()
    missing = [s.name for s in project.scans if poses.get(s.name) is None]
    if not project.scans:
        raise UsageError(f"project {path}: no scans")
    if missing:
        raise UsageError(
            f"project {path}: scan(s) {', '.join(missing)} not registered: run 'forestreg project run' first"
        )
    parts = []
    for s in project.scans:
        scan = read_scan(s.path, unit_scale=scale, scan_index=s.scan_index, with_intensity=False)
        pose = to_metres(poses[s.name], scale)
        parts.append(apply(pose, scan.points + scan.origin_shift))  # project frame (file coordinates)
    cloud = Scan.from_points(np.vstack(parts), name=path.stem, take_ownership=True)
    return cloud, f"{len(project.scans)} registered scans of project {path.name}"


def read_epoch(path, role: str, *, units: str = "m", tree_params=None, change_params=None, progress=None, cancel=None):
    """One survey (``role`` "BEFORE" or "AFTER") as :class:`~forestreg.engine.change.EpochTrees`
    and a note on what was read: a cloud's trees are measured (the tree inventory's steps, with
    ``tree_params``), a table's are taken as they are, after checking every row; the
    uncertainties, the no-ground decision and the stem band from ``change_params`` (a
    :class:`~forestreg.engine.change.ChangeParams`)."""
    epoch, note, _, _ = _read_survey(Path(path), role, units, tree_params, change_params, progress, cancel)
    return epoch, note


def _read_survey(p: Path, role: str, units: str, tree_params, change_params, progress=None, cancel=None):
    """:func:`read_epoch`, with the file the trees came from (a project's table) and the notes a
    user should see (a DBH column converted, rows left out)."""
    from ..engine.change import ChangeParams, epoch_from_cloud
    from ..engine.core.scan import Scan
    from ..engine.io import read_scan

    change_params = change_params if change_params is not None else ChangeParams()
    scale = UNITS[units]
    kind = _input_kind(p)
    if kind == "table":
        epoch, notes = _read_table(p, role, scale, change_params)
        note = f"trees table {p.name}" + (f" ({'; '.join(notes)})" if notes else "")
        return epoch, note, _real_input(p), notes
    if kind == "project":
        cloud, note = _project_cloud(p, scale)
        if not isinstance(cloud, Scan):
            epoch, notes = _read_table(cloud, role, scale, change_params)
            return epoch, note + (f" ({'; '.join(notes)})" if notes else ""), _real_input(cloud), notes
    else:
        cloud, note = read_scan(p, unit_scale=scale, with_intensity=False), f"cloud {p.name}"
    check_units(cloud, units, f"{role} {p.name}")
    check_upright(cloud, f"{role} {p.name}")
    epoch = epoch_from_cloud(
        cloud.points,
        tree_params,
        with_cancel(progress, cancel),
        origin_shift=cloud.origin_shift,
        name=role,
        change=change_params,
    )
    return epoch, f"{note}, {len(cloud.points):,} points", _real_input(p), ()


def _unit_mismatch(before, after, units_before: str, units_after: str) -> None:
    """Refuse two surveys whose tree positions differ by a unit factor
    (:func:`~forestreg.engine.change.position_unit_mismatch`), naming the units that would agree."""
    from ..engine.change import position_unit_mismatch
    from ..engine.core.errors import UsageError

    found = position_unit_mismatch(before, after)
    if found is None:
        return
    larger = found["larger"]
    given = {"BEFORE": units_before, "AFTER": units_after}
    smaller = "AFTER" if larger == "BEFORE" else "BEFORE"

    def unit_for(scale: float) -> Optional[str]:
        return next((u for u, s in UNITS.items() if abs(s / scale - 1.0) < 0.01), None)

    # the larger numbers are in a unit `factor` times the given one's, or the other survey's in one 1/factor times
    fixes = []
    u = unit_for(UNITS[given[larger]] * found["factor"])
    if u is not None:
        fixes.append(f"--units-{larger.lower()} {u}")
    u = unit_for(UNITS[given[smaller]] / found["factor"])
    if u is not None:
        fixes.append(f"--units-{smaller.lower()} {u}")
    same = units_before == units_after
    read_as = f"both read as {units_before}" if same else f"BEFORE read as {units_before}, AFTER as {units_after}"
    hint = (
        f"; give each survey's unit: {' or '.join(fixes)}"
        if fixes
        else "; give each survey's unit (--units-before, --units-after)"
    )
    raise UsageError(
        f"the two surveys look like different units ({read_as}): {found['why']}: {larger} looks like "
        f"{found['unit']} against {smaller}'s unit{hint}"
    )


def _survey_crs(path: Path, kind: str):
    """The CRS a survey's input declares, read without its points: a cloud's header; a trees
    table's ``layers.gpkg`` beside it; a project's trees folder, cloud, or centre scan."""
    from ..engine.io import read_crs
    from ..engine.io.gpkg import read_crs as gpkg_crs

    if kind == "cloud":
        return read_crs(path)
    if kind == "table":
        return gpkg_crs((path if path.is_dir() else path.parent) / "layers.gpkg")
    try:
        from ..engine.tls.project import Project

        project = Project.load(path)
    except Exception:  # noqa: BLE001 - the project is read (and its problem told) with the survey
        return None
    for name in ("ground", "fused", *project.forest.trees):
        folder = project.forest.trees.get(name)
        if folder is not None and (Path(folder) / "trees.csv").is_file():
            return gpkg_crs(Path(folder) / "layers.gpkg")
    for cloud in (project.forest.ground_cloud, project.forest.fused_cloud):
        if cloud is not None and Path(cloud).is_file():
            return read_crs(cloud)
    centre = project.centre or (project.scans[0].name if project.scans else None)
    return read_crs(project.scan(centre).path) if centre else None


def detect_change_files(
    before,
    after,
    out,
    params=None,
    *,
    units: str = "m",
    units_before: Optional[str] = None,
    units_after: Optional[str] = None,
    report: bool = True,
    crs=None,
    progress=None,
    cancel=None,
) -> ChangeOutcome:
    """Compare the surveys ``before`` and ``after`` (paths: clouds, project files, trees tables)
    into the folder ``out`` (a transaction; None: nothing written). ``params``: a
    :class:`~forestreg.engine.params.ProductParams` (its ``change`` and ``trees`` sections) or a
    :class:`~forestreg.engine.change.ChangeParams`. ``units``: the unit of both surveys' files;
    ``units_before`` / ``units_after`` one survey's, when they differ. Returns a :class:`ChangeOutcome`.

    Refused (:class:`~forestreg.engine.core.errors.UsageError` or
    :class:`~forestreg.engine.core.errors.ScanDataError`, before anything is written): the same
    file twice (also a folder and its ``trees.csv``), a table with bad rows (positions that are no
    finite number, a DBH not above 0 or in another unit, a tree listed twice), and surveys whose
    positions differ by a unit factor. The outputs are in BEFORE's frame and take its CRS, or
    ``crs`` (e.g. "EPSG:32618") when BEFORE declares none or it should win."""
    from ..engine.change import CHANGE_COLUMNS, ChangeParams, detect_change
    from ..engine.core.atomic import check_output_folder, output_folder
    from ..engine.core.errors import UsageError
    from ..engine.core.progress import as_progress
    from ..engine.io.crs import frame_crs
    from ..engine.trees.inventory import TreeParams

    units_before = units if units_before is None else units_before
    units_after = units if units_after is None else units_after
    given = given_crs(crs, units_before)
    for u in (units, units_before, units_after):
        if u not in UNITS:
            raise UsageError(f"unknown unit {u!r}: one of {', '.join(UNITS)}")
    scale, scale_after = UNITS[units_before], UNITS[units_after]
    change_params, tree_params = ChangeParams(), TreeParams()
    if isinstance(params, ChangeParams):
        change_params = params
    elif params is not None:
        change_params, tree_params = params.change, params.trees
    b_path, a_path = Path(before), Path(after)

    def same_refused(b: Path, a: Path) -> None:
        refuse_same_file(b, a, "BEFORE and AFTER are the same file: give the two surveys")

    same_refused(b_path.resolve(), a_path.resolve())
    kinds = (_input_kind(b_path), _input_kind(a_path))  # both checked before any work
    same_refused(_real_input(b_path), _real_input(a_path))
    if out is not None:
        out = check_output_folder(out, "change", inputs=[b_path, a_path])
    prog = as_progress(with_cancel(progress, cancel))
    t0 = time.perf_counter()
    b_epoch, b_note, b_real, b_notes = _read_survey(
        b_path, "BEFORE", units_before, tree_params, change_params, prog.sub(0.0, 0.45)
    )
    if kinds[0] == "project":
        same_refused(b_real, _real_input(a_path))
    a_epoch, a_note, a_real, a_notes = _read_survey(
        a_path, "AFTER", units_after, tree_params, change_params, prog.sub(0.45, 0.9)
    )
    same_refused(b_real, a_real)
    _unit_mismatch(b_epoch, a_epoch, units_before, units_after)
    read_s = time.perf_counter() - t0
    result = detect_change(b_epoch, a_epoch, change_params, prog.sub(0.9, 1.0))
    # the last check before "ok"; the matrix's translation in BEFORE's unit
    summary, ok = run_summary(
        result,
        {"read_and_trees_s": read_s},
        {"before": b_path, "after": a_path},
        units_before,
        scale,
        facts={"before_read": b_note, "after_read": a_note, "inputs": {"before": kinds[0], "after": kinds[1]}},
    )
    if summary.get("matrix") is not None:
        # file coordinates of each survey in its own unit: p_before = M @ p_after holds the unit ratio
        m = np.array(summary["matrix"], dtype=float)
        m[:3, :3] *= scale_after / scale
        summary["matrix"] = m.tolist()
    notes = [f"BEFORE: {n}" for n in b_notes] + [f"AFTER: {n}" for n in a_notes]
    summary.update(
        unit_after=units_after,
        unit_scale_after=scale_after,
        notes=notes,
        columns="tree_changes.csv: x, y in BEFORE file coordinates (BEFORE's unit); DBH and heights in metres",
    )
    frame = frame_crs(
        {"before": _survey_crs(b_path, kinds[0]), "after": _survey_crs(a_path, kinds[1])},
        "before",
        given,
        names={"before": f"BEFORE ({b_path.name})", "after": f"AFTER ({a_path.name})"},
    )
    summary["crs"] = frame.to_dict(
        frames={
            "matrix": f"maps {frame.label_of('after')} onto {frame.label_of('before')}",
            "tree_changes.csv": frame.label_of("before"),
            "layers.gpkg": frame.label_of("before"),
        }
    )
    if units_before != units_after:
        summary["convention"] = (
            f"{summary.get('convention') or ChangeOutcome.convention}; BEFORE in {units_before}, AFTER in "
            f"{units_after}: the matrix scales by {scale_after / scale:.6g}"
        )
    rows_local = [t.row(np.zeros(3)) for t in result.trees] if ok else []
    rows = [
        {
            **r,
            "x": (r["x"] + float(result.origin_shift[0])) / scale,
            "y": (r["y"] + float(result.origin_shift[1])) / scale,
        }
        for r in rows_local
    ]
    if out is not None:
        from ..engine.io.change import write_change_files

        with output_folder(out, "change") as tmp:
            if ok:
                from .layers import change_layers, write_layers

                write_change_files(tmp, summary, rows, CHANGE_COLUMNS)
                write_layers(tmp, change_layers(rows, CHANGE_COLUMNS), frame.crs)
            else:
                import json

                from ..engine.core.atomic import write_text_atomic
                from ..engine.core.jsonable import to_jsonable

                write_text_atomic(
                    tmp / "result.json", json.dumps(to_jsonable(summary, nan_as_null=True), indent=1) + "\n"
                )
            if report:
                from ..engine.report.change_report import write_change_report

                background = b_epoch.band[::7, :2] if b_epoch.has_points else None
                write_change_report(tmp, summary, rows_local, background, file_rows=rows)
    return outcome_of(summary, out=out, result=result, cls=ChangeOutcome, rows=rows, notes=tuple(notes))
