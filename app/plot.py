"""Plot and project runs: every TLS scan of a plot registered (each to the centre scan, tilted ones
to their level partner, or every pair with a pose graph), poses adjusted, and the plot folder
written (``project.json``, ``poses.json``, ``<scan>.transform.txt``, ``layers.gpkg``,
``report.html``; optionally a merged cloud, registered scans, an E57 file). Every output is in the
centre scan's frame and takes its CRS (``poses.json``'s ``crs``, the merged and registered clouds'
WKT VLR, ``layers.gpkg``).

:func:`plot_scans` is the whole ``plot`` use case from scan files, its checks first (the command,
the job service and the batch through it, and the Python API call it); :func:`new_project` builds
a project from scan files and the user's marks; :func:`run_plot` registers a project and writes
the products (``project run``, the watch); :func:`register_plot` is the registration they all
go through, its check of the scans first (:func:`check_scans_near_their_scanners`), and the
desktop's run of the project it edits (the project saved to its file, no folder written). The
rules of editing a project (no link of a scan to itself, the centre scan not moved) are the
project's own (:class:`~forestreg.engine.tls.project.Project`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from ..engine.core.uncertainty import evidence_notes
from ..engine.tls.plot import PlotOutcome, ScanCache, default_links, pose_uncertainty  # noqa: F401 - the plot's types, for the front doors
from ..engine.tls.project import Link, Project, ScanEntry  # noqa: F401 - the saved plot project
from .common import (
    RunOutcome,
    check_replaceable_point_file,
    checked_scans,
    given_crs,
    import_in_background,
    refuse_scans_given_twice,
    with_cancel,
)
from .saved import count_or_none, finite_or_none, mapping_or_empty

log = logging.getLogger("forestreg")

#: Point files a merged cloud may be written as.
POINT_SUFFIXES = (".laz", ".las", ".ply", ".xyz", ".txt")


@dataclass(frozen=True)
class PoseSigma:
    """1-sigma uncertainty of a registered pose relative to the frame scan (None where unknown):
    position error at the scanner (m) and rotation error (degrees); ``fixed`` when the survey held
    the pose fixed, ``method`` how it was found."""

    translation_m: Optional[float]
    rotation_deg: Optional[float]
    method: str = ""
    fixed: bool = False
    #: what the uncertainty says of itself: weak directions, alternatives counted or excluded
    notes: tuple[str, ...] = ()

    @classmethod
    def of(cls, d) -> Optional["PoseSigma"]:
        if not isinstance(d, Mapping) or not d:
            return None
        return cls(
            finite_or_none(d.get("translation_m")),
            finite_or_none(d.get("rotation_deg")),
            str(d.get("method") or ""),
            bool(d.get("fixed")),
            tuple(evidence_notes(dict(d))),
        )

    @property
    def known(self) -> bool:
        return self.translation_m is not None and self.rotation_deg is not None


@dataclass(frozen=True)
class DroppedLink:
    """A link the survey left out as inconsistent, and why."""

    moving: str
    reference: str
    reason: str


def dropped_links(project) -> tuple[DroppedLink, ...]:
    """The links the survey adjustment of ``project`` dropped (empty without one)."""
    return tuple(
        DroppedLink(str(d.get("moving")), str(d.get("reference")), str(d.get("reason") or ""))
        for d in mapping_or_empty(project.adjustment).get("dropped") or []
        if isinstance(d, Mapping)
    )


@dataclass(frozen=True)
class ScanQuality:
    """The survey's quality figures of one scan (None where not computed): the worst terrain
    agreement of its links (m), its worst link's ambiguity, the largest loop residual at the scanner
    (m) and how many of its links were dropped."""

    terrain_median_m: Optional[float] = None
    max_ambiguity: Optional[float] = None
    max_residual_m: Optional[float] = None
    dropped_links: Optional[int] = None


def scan_quality(project) -> dict[str, ScanQuality]:
    """Scan name -> :class:`ScanQuality` from the project's survey adjustment (empty without one)."""
    found = {}
    for name, q in mapping_or_empty(mapping_or_empty(project.adjustment).get("quality")).items():
        q = mapping_or_empty(q)
        found[str(name)] = ScanQuality(
            finite_or_none(q.get("terrain_median_m")),
            finite_or_none(q.get("max_ambiguity")),
            finite_or_none(q.get("max_residual_m")),
            count_or_none(q.get("dropped_links")),
        )
    return found


def pose_sigmas(project) -> dict[str, Optional[PoseSigma]]:
    """Scan name -> the 1-sigma uncertainty of its pose (:func:`pose_uncertainty`; None where
    unknown); empty without a centre scan or when a link of an older project lacks the figures."""
    if not project.scans or not project.centre:
        return {}
    try:
        found = pose_uncertainty(project)
    except (KeyError, ValueError, TypeError):  # links of an older project without the figures
        return {}
    return {name: PoseSigma.of(u) for name, u in found.items()}


@dataclass(frozen=True)
class LinkSummary:
    """What a project shows of one link's last run: status, reason, the search radius D_r (m),
    trunk shadows (VOPs) of each scan, matched VOPs, the fine fit (ICP std in m, overlap), the VOP
    residual (m), the pair's uncertainty, the terrain agreement (m), the ambiguity and the number
    of failed attempts before it was placed."""

    reference: str
    status: str
    matched: Any = None
    icp_std_m: Optional[float] = None
    reason: str = ""
    icp_fitness: Optional[float] = None
    vop_radius_m: Optional[float] = None
    reference_vops: Optional[int] = None
    moving_vops: Optional[int] = None
    vop_residual_m: Optional[float] = None
    uncertainty: Optional[PoseSigma] = None
    terrain_median_m: Optional[float] = None
    ambiguity: Optional[float] = None
    retried: int = 0

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def link_summary(link) -> Optional[LinkSummary]:
    """The :class:`LinkSummary` of a link (None when it has not run)."""
    if link is None or link.result is None:
        return None
    r = link.result
    icp, quality = mapping_or_empty(r.get("icp")), mapping_or_empty(r.get("quality"))
    return LinkSummary(
        link.reference,
        r.status,
        r.get("matched"),
        finite_or_none(icp.get("std_m")),
        r.reason,
        icp_fitness=finite_or_none(icp.get("fitness")),
        vop_radius_m=finite_or_none(r.get("vop_radius_m")),
        reference_vops=count_or_none(r.get("reference_vops")),
        moving_vops=count_or_none(r.get("moving_vops")),
        vop_residual_m=finite_or_none(r.get("vop_residual_m")),
        uncertainty=PoseSigma.of(r.get("uncertainty")),
        terrain_median_m=finite_or_none(quality.get("terrain_median_m")),
        ambiguity=finite_or_none(quality.get("ambiguity")),
        retried=len(r.get("retried_after") or ()),
    )


@dataclass(frozen=True, eq=False)
class PlotRun(RunOutcome):
    """A plot run: ``result`` is the engine's :class:`~forestreg.engine.tls.plot.PlotOutcome`
    (per scan "ok"/"failed"/"centre" and the reasons), ``project`` the registered project,
    ``adjusted`` the global adjustment (or None), ``uncertainty`` per scan (1 sigma), ``written``
    the extra products (what -> (path, count)). Failed when a scan could not be registered."""

    method = "auto (trunk shadows + ICP), per link"
    project: Any = None
    adjusted: Optional[dict] = None
    uncertainty: dict = field(default_factory=dict)
    written: dict = field(default_factory=dict)
    #: links the survey dropped (:class:`DroppedLink`)
    dropped: tuple = ()
    #: after the global adjustment: (links adjusted, largest link residual in m), or None
    residual: Optional[tuple] = None
    #: the CRS of the outputs (the centre scan's) and each scan's (:class:`~forestreg.engine.io.crs.FrameCrs`)
    crs: Any = None

    def evidence(self) -> dict:
        return self.result.evidence() if self.result is not None else {}


# ----------------------------------------------------------------------------- inputs


def check_scan_files_exist(paths: Sequence) -> None:
    """A missing scan is a typo (exit 2, before any work); an existing but unreadable scan is
    reported as failed while the others are registered. A plot needs two scans (or one multi-scan
    E57 file), each given once."""
    from ..engine.core.errors import ScanReadError, UsageError

    if len(paths) == 1 and Path(paths[0]).suffix.lower() != ".e57":
        raise UsageError(f"a plot needs at least two scans (or one multi-scan E57 file); got only {paths[0]}")
    refuse_scans_given_twice(paths)
    for p in paths:
        if not Path(p).exists():
            raise ScanReadError(f"{p}: no such file")
        if Path(p).is_dir():
            raise ScanReadError(f"{p}: is a folder, not a scan file")


def check_scan_files(paths: Sequence) -> None:
    """Every scan can be read (missing, empty, corrupt or garbage files: one line, exit 2)."""
    from ..engine.io import read_scan
    from ..engine.io.base import check_readable

    for p in paths:
        if Path(p).suffix.lower() == ".e57":
            check_readable(p)
            continue
        read_scan(p)


def check_extra_outputs(inputs: Sequence, *, merged=None, e57_out=None, registered_dir=None, out=None) -> None:
    """A merged cloud, an E57 file and a folder of registered scans: refused before the work when
    they would overwrite an input or a file of another kind. A file inside ``out`` (the plot's
    output folder, e.g. ``--merged plot/all.copc.laz``) may lie in a folder the run makes."""
    from ..engine.core.atomic import check_output_folder

    if merged:
        _check_extra_file(merged, inputs, POINT_SUFFIXES, out)
        check_replaceable_point_file(merged, "scan_id", "merged cloud")
    if e57_out:
        _check_extra_file(e57_out, inputs, (".e57",), out)
        _check_replaceable_e57(e57_out)
    if registered_dir:
        check_output_folder(registered_dir, "registered-scans", inputs=inputs)


def _check_replaceable_e57(path) -> None:
    """An existing E57 file at an output path is replaced only when forestreg wrote every scan of
    it (an earlier ``--e57-out``); a scanner's or another program's E57 is refused."""
    from ..engine.core.errors import OutputPathError
    from ..engine.io.e57 import written_by_forestreg

    p = Path(path)
    if p.exists() and not written_by_forestreg(p):
        raise OutputPathError(
            f"{p} exists and is not an earlier E57 output of forestreg: it would be overwritten; give a new file name"
        )


def _check_extra_file(path, inputs: Sequence, suffixes: tuple[str, ...], out) -> None:
    """:func:`~forestreg.engine.core.atomic.check_output_file`, except that a file inside ``out``
    whose folder does not exist yet is only checked for its suffix: the run makes that folder with
    the output folder (which is checked itself), and no input can lie in it."""
    from ..engine.core.atomic import check_output_file
    from ..engine.core.errors import OutputPathError

    target = Path(path).expanduser().resolve()
    if out is not None and not target.parent.is_dir() and Path(out).expanduser().resolve() in target.parents:
        if target.suffix.lower() not in suffixes:
            raise OutputPathError(f"{path}: the output must end in {' or '.join(suffixes)}")
        return
    check_output_file(path, inputs=inputs, suffixes=suffixes)


def new_project(
    scans: Sequence,
    params,
    *,
    name: str = "plot",
    centre: Optional[str] = None,
    tilted: Sequence[str] = (),
    targets: Optional[str] = None,
    positions: Optional[str] = None,
    prior_poses: Optional[str] = None,
    fixed: Sequence[str] = (),
    scanner_params=None,
):
    """A new :class:`~forestreg.engine.tls.project.Project` from scan files (or one multi-scan
    E57 file), the centre scan, tilted marks (``SCAN[:PARTNER],...``), a targets CSV, scanner
    positions, prior poses, fixed scans and the scanner-position settings (``scanner_params``, for
    scans whose files do not say where their scanner stood). A name that is not one of the scans raises
    :class:`~forestreg.engine.core.errors.UsageError`."""
    from ..engine.core.errors import UsageError
    from .survey import survey_inputs

    if len(scans) == 1 and Path(scans[0]).suffix.lower() == ".e57":
        from ..engine.tls.plot import project_from_e57

        project = project_from_e57(scans[0])
        project.params = params
    else:
        project = Project(name=name, params=params)
        for path in scans:
            project.add_scan(path)
    if scanner_params is not None:
        project.scanner_params = scanner_params
    names = {Path(p).name: s.name for p, s in zip(scans, project.scans)} if len(scans) == len(project.scans) else {}

    def known(name: str, option: str) -> str:
        resolved = names.get(Path(name).name, name)
        if not project.has_scan(resolved):
            raise UsageError(
                f"{option} {name}: not one of the plot's scans ({', '.join(s.name for s in project.scans)})"
            )
        return resolved

    if centre:
        project.centre = known(centre, "--centre")
    for item in ",".join(tilted or []).split(","):
        if not item.strip():
            continue
        moving, _, partner = item.partition(":")
        entry = project.scan(known(moving, "--tilted"))
        entry.tilted = True
        if partner:
            other = known(partner, "--tilted")
            if other == entry.name:
                raise UsageError(f"--tilted {item}: a scan cannot be its own level partner")
            entry.level_partner = other
    survey_inputs(project, known, positions=positions, prior_poses=prior_poses, fixed=fixed)
    if targets:
        from ..engine.tls.manual import read_targets_csv

        for scan_name, found in read_targets_csv(targets).items():
            if project.has_scan(scan_name):
                project.scan(scan_name).targets = found
            else:
                log.warning("targets for %s: no such scan in the plot", scan_name)
    return project


def load_project(path):
    """A saved :class:`~forestreg.engine.tls.project.Project`."""
    return Project.load(path)


def scan_cache(project, *, with_intensity: bool = True):
    """The plot's scans, read once and prepared on demand
    (:class:`~forestreg.engine.tls.plot.ScanCache`)."""
    return ScanCache(project, with_intensity=with_intensity)


def check_scans_near_their_scanners(project, scans) -> None:
    """Before the work: when no scan of the plot is in metres with points near its scanner
    (georeferenced scans without scanner positions, or files in cm/mm), refuse with one line
    instead of failing every link after minutes (:func:`~forestreg.app.common.checked_scans`, the
    Python API's check too). A single such scan fails its own link with the reason."""
    checked_scans(project, scans)


def plot_folder(out, scans: Sequence) -> Path:
    """The plot's working folder: absent, empty or an earlier plot folder (marked)."""
    from ..engine.core.atomic import MARKER, check_output_folder

    folder = check_output_folder(out, "plot", inputs=scans)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / MARKER).write_text("plot\n", encoding="utf-8")
    return folder


def resumable_project(out, project: Project) -> tuple[Project, int]:
    """The project to run into ``out``: the one a stopped run of the same plot saved there, with
    the links it registered, or ``project`` itself.

    A ``plot`` run saves ``out/project.json`` after every link and writes ``poses.json`` only at
    its end. A folder with the project file but without ``poses.json`` is an unfinished run
    (killed, out of memory, power lost); when its scans, centre, tilted marks, targets, positions
    and parameters are those of ``project``, its links are the ones this run would make, and no
    scan file changed after that run began, its registered links are kept. Returns (the project,
    links kept); anything else (no such folder, a finished run, other settings, a damaged file)
    gives ``(project, 0)`` and the run starts over."""
    from ..engine.core.atomic import MARKER
    from ..engine.tls.project import ProjectFileError

    folder = Path(out)
    saved_file = folder / "project.json"
    try:
        if (folder / MARKER).read_text(encoding="utf-8").strip() != "plot" or (folder / "poses.json").exists():
            return project, 0
        saved = Project.load(saved_file)
        started = (folder / MARKER).stat().st_mtime  # written when the stopped run began
        if any(Path(s.path).stat().st_mtime >= started for s in project.scans):
            return project, 0
    except (OSError, UnicodeDecodeError, ProjectFileError):
        return project, 0
    default_links(project)

    def settings(p: Project) -> dict:
        d = p.to_dict(relative_to=folder)
        d.pop("adjustment", None)
        d.pop("forest", None)
        d["links"] = [{k: v for k, v in link.items() if k != "result"} for link in d["links"]]
        return d

    done = sum(1 for link in saved.links if link.ok)
    if not done or settings(saved) != settings(project):
        return project, 0
    return saved, done


# ----------------------------------------------------------------------------- the run


def register_plot(
    project,
    scans=None,
    *,
    pairs: Optional[str] = None,
    fixed: Sequence[str] = (),
    rerun: bool = False,
    loops: Optional[float] = None,
    survey=None,
    progress=None,
    cancel=None,
    on_link: Optional[Callable[[Any], None]] = None,
):
    """The registration of every plot run (:func:`plot_scans`, :func:`run_plot`, the desktop's run
    of the project it edits): the scans checked first (:func:`check_scans_near_their_scanners`: a
    plot the ``plot`` command refuses is refused here, before any link runs), then the links
    (``pairs``: every pair with a pose graph, see :mod:`forestreg.app.survey`, with the other
    settings of ``survey``; ``loops``: also links between scans within that many metres), the
    global adjustment, and the project saved to its file (when it has one) after each finished
    link and at the end. ``on_link(link)`` after each link to the centre. Returns the engine's
    :class:`~forestreg.engine.tls.plot.PlotOutcome`; the poses and the adjustment are in the
    project."""
    from ..engine.io.results import save_to_its_file
    from ..engine.tls.plot import add_neighbour_links, adjust_poses, register_project

    scans = checked_scans(project, scans)  # before any link runs
    step = with_cancel(progress, cancel)
    if pairs:
        from .survey import register_survey

        outcome = register_survey(
            project,
            pairs,
            fixed=fixed,
            rerun=rerun,
            scans=scans,
            progress=step,
            base=survey,
            on_link_done=save_to_its_file,
        )
    else:
        report = step or (lambda f, m: None)
        outcome = register_project(
            project,
            rerun=rerun,
            progress=lambda f, m: report(0.95 * f, m),
            cancel=cancel,
            scans=scans,
            on_link=on_link,
            on_link_done=save_to_its_file,
        )
        if loops:
            added = add_neighbour_links(project, loops)
            if added:
                log.info("closing %d loops between neighbouring scans", len(added))
                register_project(project, progress=step, scans=scans, cancel=cancel, on_link_done=save_to_its_file)
        if cancel is not None:
            cancel.raise_if_cancelled()
        report(0.96, "global adjustment")
        adjust_poses(project, scans)
        report(1.0, "done")
    save_to_its_file(project)
    return outcome


def plot_scans(
    scan_files: Sequence,
    out,
    params=None,
    *,
    centre: Optional[str] = None,
    tilted: Sequence[str] = (),
    targets=None,
    positions=None,
    prior_poses=None,
    fixed: Sequence[str] = (),
    scanner_params=None,
    pairs: Optional[str] = None,
    loops: Optional[float] = None,
    merged=None,
    registered_dir=None,
    e57_out=None,
    survey=None,
    crs=None,
    on_resume: Optional[Callable[[Path, int, int], None]] = None,
    progress=None,
    cancel=None,
) -> PlotRun:
    """The whole ``plot`` use case, for every front door (the ``plot`` command, the job service
    and the batch through it, the Python API): the checks before any work (the survey options,
    ``crs``, the scan files, the extra outputs, the scans near their scanners), the project from
    the scan files and marks (:func:`new_project`), a stopped run of the same plot in ``out`` gone
    on with (:func:`resumable_project`; not with ``pairs`` or ``loops``), the folder made and the
    project saved in it, then :func:`run_plot`. ``on_resume(out, kept, links)`` is told when links
    of a stopped run are kept. Returns the :class:`PlotRun`."""
    from ..engine.tls.params import RegistrationParams
    from .survey import check_survey_options

    params = params if params is not None else RegistrationParams()
    check_survey_options(pairs, positions, prior_poses)
    given_crs(crs, "m")  # a bad crs, or one the scans cannot be in: refused before the folder is made
    check_scan_files_exist(scan_files)
    check_extra_outputs(scan_files, out=out, merged=merged, e57_out=e57_out, registered_dir=registered_dir)
    project = new_project(
        scan_files,
        params,
        name=Path(out).name,
        centre=centre,
        tilted=list(tilted or []),
        targets=targets,
        positions=positions,
        prior_poses=prior_poses,
        fixed=list(fixed or []),
        scanner_params=scanner_params,
    )
    kept = 0
    if not pairs and not loops:
        project, kept = resumable_project(out, project)  # a stopped run of the same plot goes on
    scans = scan_cache(project, with_intensity=bool(merged or registered_dir or e57_out))
    check_scans_near_their_scanners(project, scans)  # before anything is written
    folder = plot_folder(out, scan_files)
    if kept and on_resume is not None:
        on_resume(folder, kept, len(project.links))
    project.save(folder / "project.json")
    return run_plot(
        project,
        folder,
        scans=scans,
        pairs=pairs,
        fixed=fixed or [],
        loops=loops,
        merged=merged,
        registered_dir=registered_dir,
        e57_out=e57_out,
        survey=survey,
        crs=crs,
        progress=progress,
        cancel=cancel,
    )


def run_plot(
    project,
    out: Path,
    *,
    scans=None,
    pairs: Optional[str] = None,
    fixed: Sequence[str] = (),
    rerun: bool = False,
    loops: Optional[float] = None,
    merged=None,
    registered_dir=None,
    e57_out=None,
    survey=None,
    crs=None,
    progress=None,
    cancel=None,
) -> PlotRun:
    """Register the project (``pairs``: every pair with a pose graph, see
    :mod:`forestreg.app.survey`, with the other settings of ``survey``, a
    :class:`~forestreg.engine.tls.params.SurveyParams`; ``loops``: also link scans within that
    many metres), then write
    poses, transforms, ``layers.gpkg`` and the report into ``out`` (each product replaced by one
    rename, poses.json last) and the extra products asked for, all in the centre scan's frame with
    its CRS (``crs``, e.g. "EPSG:32618", when its file declares none, or the one that wins)."""
    from ..engine.core.atomic import temporary_folder

    given = given_crs(crs, "m")

    # the report's figures need matplotlib (~0.4 s of imports): loaded while the scans are
    # registered, not on the single thread that writes the report at the end
    import_in_background(".engine.report.plot_report", kernels=True)
    if scans is None:
        scans = scan_cache(project, with_intensity=bool(merged or registered_dir or e57_out))
    outcome = register_plot(
        project,
        scans,
        pairs=pairs,
        fixed=fixed,
        rerun=rerun,
        loops=loops,
        survey=survey,
        progress=progress,
        cancel=cancel,
    )
    adjusted = project.adjustment
    frame = plot_crs(project, scans, given)
    frames = {
        "poses.json": "each matrix maps a scan's file coordinates (its own frame) into the centre scan's frame",
        "layers.gpkg": "the centre scan's frame",
    }
    for path in (merged, registered_dir):
        if path:
            frames[str(Path(path).name)] = "the centre scan's frame"
    out.mkdir(parents=True, exist_ok=True)
    tmp = temporary_folder(out, "products")
    try:
        write_poses(project, tmp, outcome, crs=frame.to_dict(frames=frames))
        try:
            from .layers import plot_layers, write_layers

            write_layers(tmp, plot_layers(project, scans, pose_uncertainty(project), outcome), frame.crs)
        except Exception as exc:  # the layers must never lose the result
            log.warning("could not write layers.gpkg: %s", exc)
        try:
            from ..engine.report.plot_report import write_plot_report

            write_plot_report(project, tmp / "report.html", scans=scans)
        except Exception as exc:  # a report must never lose the result
            log.warning("could not write the report: %s", exc)
        outputs = _publish(tmp, out, [s.name for s in project.scans])
    except BaseException:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
        raise
    written: dict = {}
    for extra in (merged, e57_out):
        if extra:
            Path(extra).parent.mkdir(parents=True, exist_ok=True)  # a file inside ``out`` may lie in a folder made now
    if merged:
        written["merged"] = (Path(merged), write_merged(project, merged, scans, crs=frame.crs))
    if registered_dir:
        from ..engine.core.atomic import output_folder

        with output_folder(registered_dir, "registered-scans") as rtmp:
            written["registered_dir"] = (
                Path(registered_dir),
                write_registered_scans(project, rtmp, scans, crs=frame.crs),
            )
    if e57_out:
        written["e57_out"] = (Path(e57_out), write_registered_e57(project, e57_out, scans))
    if project.path is not None:
        outputs.append(Path(project.path))
    outputs += [path.resolve() for path, _ in written.values()]
    dropped = dropped_links(project)
    residual = None
    if adjusted:
        residual = (len(adjusted["links"]), max((r["after"]["translation_m"] for r in adjusted["links"]), default=0.0))
    return PlotRun(
        status=outcome.status,
        reason=outcome.reason,
        out=out,
        result=outcome,
        project=project,
        adjusted=adjusted,
        uncertainty={name: PoseSigma.of(u) for name, u in pose_uncertainty(project).items()},
        written=written,
        dropped=dropped,
        residual=residual,
        crs=frame,
        result_file=(out / "poses.json").resolve(),
        outputs=tuple(dict.fromkeys(outputs)),
    )


def plot_crs(project, scans=None, given=None):
    """The CRS of a plot's outputs (:class:`~forestreg.engine.io.crs.FrameCrs`): the centre scan's
    (or ``given``), and each scan's as its file declares it (a LAS/LAZ header read, not its points;
    other formats from the scan read for the run)."""
    from ..engine.io import read_crs
    from ..engine.io.crs import crs_of, frame_crs

    found = {}
    for s in project.scans:
        if Path(s.path).suffix.lower() in (".las", ".laz"):
            found[s.name] = read_crs(s.path)
            continue
        try:
            found[s.name] = crs_of(scans.frame(s.name)) if scans is not None else None
        except Exception:  # noqa: BLE001 - an unreadable scan: its link reports it
            found[s.name] = None
    centre = project.centre or (project.scans[0].name if project.scans else "")
    return frame_crs(found, centre, given, names={s.name: Path(s.path).name for s in project.scans})


def _publish(tmp: Path, out: Path, scan_names) -> list[Path]:
    """Move the finished products from ``tmp`` into ``out`` (each by one rename; poses.json last,
    so a poses.json always belongs to the transforms beside it), and drop the stale transforms of
    the project's scans (no other file). Returns the products' paths in ``out`` (absolute)."""
    import os
    import shutil

    for name in scan_names:
        stale = out / f"{name}.transform.txt"
        if stale.is_file() and not (tmp / stale.name).exists():
            stale.unlink()
    files = sorted(tmp.iterdir(), key=lambda p: p.name == "poses.json")
    for f in files:
        target = out / f.name
        if f.is_dir():
            if target.exists():
                shutil.rmtree(target)
        os.replace(f, target)
    shutil.rmtree(tmp, ignore_errors=True)
    return [(out / f.name).resolve() for f in files]


# ----------------------------------------------------------------------------- products


def write_poses(project, out_dir, outcome=None, *, crs: Optional[dict] = None) -> Path:
    """Write ``poses.json`` (``{"frame": centre, "scans": {name: {"status", "matrix"}}}``, each
    matrix mapping that scan's file coordinates into the centre scan's; with ``crs``, the
    ``result.json``-style ``crs`` entry of the centre frame) and one ``<scan>.transform.txt`` per
    registered scan. Returns the path of ``poses.json``."""
    from ..engine.io.results import write_poses_files
    from ..engine.tls.plot import poses_document

    body, transforms = poses_document(project, outcome)
    if crs is not None:
        body["crs"] = crs
    return write_poses_files(out_dir, body, transforms)


def write_merged(project, path, scans=None, *, crs=None) -> int:
    """Write every registered scan, in the centre scan's file coordinates, into one point file
    with a ``scan_id`` per point (the scan's index in the project). Returns the point count.

    LAS/LAZ are written one scan at a time, so a plot larger than memory can be merged; a
    ``*.copc.laz`` path gives a COPC file, also out of core; intensities are written when every
    scan has them; ``crs`` (the centre scan's, a :class:`~forestreg.engine.io.crs.Crs`) goes into
    the LAS/LAZ/COPC header."""
    from ..engine.io import write_point_chunks
    from ..engine.tls.plot import merged_chunks

    chunks, bounds, with_intensity = merged_chunks(project, path, scans)
    return write_point_chunks(path, chunks, bounds=bounds, with_intensity=with_intensity, with_scan_id=True, crs=crs)


def write_registered_e57(project, path, scans=None) -> int:
    """Write the registered scans into one E57 file, each with its registered pose (its own
    coordinates -> the centre scan's). Returns how many scans were written."""
    from ..engine.io import write_e57
    from ..engine.tls.plot import registered_scans

    chosen = registered_scans(project, scans)
    write_e57(path, [scan() for _, scan, _ in chosen], [pose for _, _, pose in chosen])
    return len(chosen)


def write_registered_scans(project, folder, scans=None, *, suffix: str = ".laz", crs=None) -> int:
    """Write each registered scan, transformed into the centre scan's file coordinates, as its own
    file ``<folder>/<scan stem>_registered<suffix>`` (with ``crs``, the centre scan's CRS). Returns
    how many were written."""
    from ..engine.io import write_scan
    from ..engine.tls.plot import registered_scans

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    for name, scan, pose in registered_scans(project, scans):
        stem = Path(name).stem if Path(name).suffix else name
        write_scan(scan(), out / f"{stem.replace('#', '_')}_registered{suffix}", matrix=pose, crs=crs)
        written += 1
    return written
