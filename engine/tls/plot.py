"""Multi-scan plot registration: linking, retries, composing poses, and global adjustment.

The paper registers every scan to the centre scan, and a tilted scan to the level scan at the same
spot. A surveyor whose link fails tries the scans already registered, nearest first; what cannot be
registered is reported, never guessed. Where extra links close loops, a pose graph spreads the error
(like RiSCAN's multi-station adjustment).

Frames: see :mod:`forestreg.engine.tls.project` (poses map a scan's file coordinates into the centre
scan's file coordinates).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from ..core.errors import DataError, InvalidArgumentError, ScanDataError, ScanReadError
from ..core.imports import import_open3d
from ..core.outcome import Outcome
from ..core.progress import CancelToken, Progress, ProgressCallback
from ..core.scan import Scan
from ..core.transform import apply as apply_transform
from ..core.transform import format_matrix, rigid_errors
from ..geometry.voxel import voxel_downsample
from ..io import read_scan
from ..io.las import intensity_to_uint16, las_header_bounds
from .pair import SEQUENTIAL_PREPARE_POINTS, register
from .prepare import PREPARED_BYTES_PER_POINT, PreparedScans, scan_identity
from .project import Link, LinkResult, Project, ScanEntry
from .scanner_position import locate_scanner

log = logging.getLogger("forestreg")


class ScanCache:
    """Reads the scans of a project on first use and keeps the most recently used ones in memory,
    up to ``max_bytes`` of point arrays (default :data:`SCAN_CACHE_BYTES`), so a plot of many large
    scans never holds them all: one scan over the budget is still read, used and then let go.

    A scanner position found from the data (:func:`locate_scanner`) is remembered, so a scan read
    again is not searched again. ``prepared`` keeps the scans prepared for registration (reduced,
    levelled, sliced, their VOPs) for the links, within half of ``max_bytes`` when one is given,
    else :data:`PREPARED_CACHE_BYTES`.

    Thread-safe: one scan is read and prepared by one thread at a time (a thread asking for a scan
    another is reading or preparing waits for it, then finds it kept); different scans may be read
    and prepared at once (:func:`register_project` prepares the next link's scan while a link runs).
    """

    def __init__(self, project: Project, max_bytes: Optional[int] = None, *, with_intensity: bool = True) -> None:
        """``with_intensity=False``: the scans are read without intensity (registration, reports and
        comparisons use the coordinates alone; merged and registered scans written from this
        cache would lack it)."""
        self.project = project
        self.with_intensity = with_intensity
        self.max_bytes = SCAN_CACHE_BYTES if max_bytes is None else int(max_bytes)
        self._lock = threading.RLock()  # the dictionaries below
        self._scan_locks: dict[str, threading.RLock] = {}  # one per scan: its reading and preparing
        self._small: Optional[bool] = None
        #: whether a scan's points stay kept once it is prepared (False: links run on the kept
        #: preparations and nothing else of the run needs the points, e.g. a survey of small scans)
        self.keep_prepared_points = True
        self._scans: OrderedDict[str, Scan] = OrderedDict()
        self._located: dict[str, tuple[np.ndarray, np.ndarray, dict[str, Any]]] = {}
        #: each scan read: its frame (the scan without points) and its identity for prepared scans
        self._frames: dict[str, tuple[Scan, tuple]] = {}
        #: how many times a scan file was read (a scan read twice was let go in between)
        self.reads = 0
        #: the scans prepared for registration, shared by the links (each scan prepared once)
        self.prepared = PreparedScans(
            max_bytes=PREPARED_CACHE_BYTES if max_bytes is None else max(int(max_bytes) // 2, 1)
        )

    def __call__(self, name: str, *, keep: bool = True) -> Scan:
        """The scan ``name`` (read unless kept). ``keep=False``: a scan not in memory is read and
        handed over without being kept (for a single pass over the plot, e.g. merging)."""
        with self._scan_lock(name):
            with self._lock:
                if name in self._scans:
                    self._scans.move_to_end(name)
                    return self._scans[name]
            entry = self.project.scan(name)
            if keep:
                with self._lock:
                    self._make_room(_file_scan_bytes(entry.path))
            scan = read_scan(
                entry.path,
                scanner_position=entry.scanner_position,
                scan_index=entry.scan_index,
                with_intensity=self.with_intensity,
            )
            with self._lock:
                self.reads += 1
                known = self._located.get(name)
            if known is not None and np.array_equal(known[1], scan.origin_shift):
                scan = dataclasses.replace(scan, scanner_position=known[0], meta=known[2])
            else:
                scan = locate_scanner(scan, self.project.scanner_params)
            with self._lock:
                self._located[name] = (scan.scanner_position, scan.origin_shift, scan.meta)
                self._frames[name] = (scan.without_points(), scan_identity(scan))
                if not keep:
                    return scan
                self._scans[name] = scan
                self._make_room(0)
            return scan

    @property
    def small(self) -> bool:
        """Whether the project's scans are :func:`small_scans` (their headers read once, when first
        asked). Then the next link's scan is prepared ahead, a survey's further pairs run beside the
        links and two at a time, and links keep each scan's ICP search structures for the next link
        on the same reference (their room is what a small plot's caches leave)."""
        if self._small is None:
            self._small = small_scans(self.project, self, [s.name for s in self.project.scans])
        return self._small

    def is_prepared(self, name: str, params) -> bool:
        """Whether the scan ``name``'s preparation for ``params`` is kept."""
        known = self._frames.get(name)
        return known is not None and self.prepared.kept(known[1], params) is not None

    def let_go_of_points(self) -> None:
        """Let go of the kept scans' points (frames, scanner positions and preparations stay):
        links whose scans are kept prepared run on stand-ins without them, and a scan needed
        whole again is read again."""
        with self._lock:
            self._scans.clear()

    def _scan_lock(self, name: str) -> threading.RLock:
        with self._lock:
            return self._scan_locks.setdefault(name, threading.RLock())

    def clear(self) -> None:
        """Let go of every kept scan and preparation (scanner positions and frames stay known)."""
        with self._lock:
            self._scans.clear()
        self.prepared.clear()

    def frame(self, name: str) -> Scan:
        """The scan ``name`` without its points (frame, scanner position, name, facts): read once,
        then known without reading the points again."""
        if name not in self._frames:
            self(name)
        return self._frames[name][0]

    def point_count(self, name: str) -> int:
        """How many points the scan ``name`` has (read once, then known)."""
        self.frame(name)
        return int(self._frames[name][1][2])

    def outline(self, name: str, params) -> Optional[tuple[np.ndarray, dict]]:
        """What the preparation of scan ``name`` for ``params`` left for drawing, kept or let go
        (:meth:`~forestreg.engine.tls.prepare.PreparedScans.outline`), without reading the scan;
        None when it was not prepared in this run."""
        known = self._frames.get(name)
        return None if known is None else self.prepared.outline(known[1], params)

    def for_link(self, name: str, params, *, prepare: bool = True) -> Scan:
        """The scan ``name`` for a link registered with ``params``: when its preparation is kept
        (or, with ``prepare``, made now), a stand-in without points that carries it
        (:meth:`~forestreg.engine.tls.prepare.PreparedScans.stand_in`), so the link does not hold
        the scan's points; otherwise the scan itself."""
        with self._scan_lock(name):
            known = self._frames.get(name)
            prepared = None if known is None else self.prepared.kept(known[1], params)
            if prepared is None:
                if not prepare:
                    return self(name)
                prepared = self.prepared.get(self(name), params)
                known = self._frames[name]
                if not self.keep_prepared_points:
                    with self._lock:
                        self._scans.pop(name, None)
            return self.prepared.stand_in(known[0], known[1], prepared, params)

    def _make_room(self, incoming: int) -> None:
        """Let go of the least recently used scans until the kept ones and ``incoming`` bytes fit
        in ``max_bytes`` (the most recently used one stays): done before a read, so a scan being
        read does not sit beside one that is about to be dropped."""
        while self._scans and sum(_scan_bytes(s) for s in self._scans.values()) + incoming > self.max_bytes:
            if len(self._scans) == 1 and not incoming:
                break
            self._scans.popitem(last=False)

    def bounds(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corner of a scan's points (file coordinates, metres): from a LAS/LAZ
        header without reading the points, else from the points."""
        entry = self.project.scan(name)
        if name not in self._scans and entry.path.suffix.lower() in (".las", ".laz"):
            try:
                stated = las_header_bounds(entry.path)
            except (ScanReadError, OSError):  # a damaged or missing file: the read below says what is wrong
                stated = None
            if stated is not None:
                return stated
        scan = self(name)
        return scan.points.min(axis=0) + scan.origin_shift, scan.points.max(axis=0) + scan.origin_shift


#: Point arrays a :class:`ScanCache` keeps in memory by default, bytes: some twelve 3 M-point
#: scans, or one 30 M-point scan (a 0.04 deg RIEGL scan, 0.8 GB). A link holds one scan's points
#: at a time (its reference is prepared first and kept prepared, :meth:`ScanCache.for_link`), so
#: with :data:`PREPARED_CACHE_BYTES` a plot of 30 M-point scans registers within 4 GB.
SCAN_CACHE_BYTES = 1_000_000_000
#: Prepared scans (:class:`~forestreg.engine.tls.prepare.PreparedScans`) a :class:`ScanCache`
#: keeps for its links by default, bytes: the centre scan and the scan being linked to it when
#: both are 30 M-point scans (0.55 GB each prepared; a 3 M-point scan holds about 60 MB).
PREPARED_CACHE_BYTES = 1_500_000_000


def _scan_bytes(scan: Scan) -> int:
    return int(scan.points.nbytes + (0 if scan.intensity is None else scan.intensity.nbytes))


#: Bytes per point in :func:`_file_scan_bytes`' estimate.
_FILE_BYTES_PER_POINT = 3 * 8 + 2


def _file_scan_bytes(path: Path) -> int:
    """Bytes the points of a LAS/LAZ file take once read (float64 x, y, z and a uint16 intensity),
    from its header; 0 for other formats or an unreadable header (the read then says why)."""
    if Path(path).suffix.lower() not in (".las", ".laz"):
        return 0
    from ..io.las import check_las_header

    try:  # the header checked first: laspy itself would walk a damaged header's VLR counts (GBs)
        return check_las_header(Path(path))[0] * _FILE_BYTES_PER_POINT
    except (ScanReadError, OSError):  # a damaged or missing file: no estimate (the read says what is wrong)
        return 0


@dataclass(eq=False)
class PlotOutcome(Outcome):
    """What a plot run did: ``scans`` per scan "ok"/"failed"/"centre", and the reasons of failures
    (``reasons``). Its ``status`` is "ok" when no scan failed, else "failed" with the reasons;
    the poses are in the project (``matrix`` None)."""

    scans: dict[str, str] = field(default_factory=dict)
    reasons: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)

    method = "auto (trunk shadows + ICP), per link"
    convention = "each scan's pose in the project"
    matrix = None

    @property
    def status(self) -> str:  # type: ignore[override]
        return "failed" if self.failed else "ok"

    @property
    def reason(self) -> str:  # type: ignore[override]
        return "; ".join(f"{name}: {self.reasons.get(name) or 'failed'}" for name in self.failed)

    @property
    def registered(self) -> list[str]:
        return [k for k, v in self.scans.items() if v in ("ok", "centre")]

    @property
    def failed(self) -> list[str]:
        return [k for k, v in self.scans.items() if v == "failed"]

    def evidence(self) -> dict[str, Any]:
        return {"scans": dict(self.scans), "reasons": dict(self.reasons)}


def default_links(project: Project) -> None:
    """Give every scan without a link the paper's default: tilted scans to their level partner,
    the rest to the centre scan. A tilted scan without a named partner is linked to the centre
    for now; :func:`register_project` looks for its partner among the level scans."""
    if project.centre is None:
        raise InvalidArgumentError("the project has no scans")
    for s in project.scans:
        if s.name == project.centre or project.link_of(s.name) is not None:
            continue
        reference = s.level_partner if (s.tilted and s.level_partner) else project.centre
        project.set_link(s.name, reference)


def register_project(
    project: Project,
    *,
    rerun: bool = False,
    progress: Optional[ProgressCallback] = None,
    cancel: Optional[CancelToken] = None,
    on_link: Optional[Callable[[Link], None]] = None,
    on_link_done: Optional[Callable[[Project], None]] = None,
    scans: Optional[ScanCache] = None,
    beside: Optional[LinkQueue] = None,
) -> PlotOutcome:
    """Register every scan of the project along its link, retrying failed links.

    Links that already succeeded are kept unless ``rerun``. After each finished link (placing or
    extra) ``on_link_done(project)`` is called, then, for a placing link, ``on_link(link)``: the
    caller keeps what is done there (the use cases save the project file, so an interrupted run
    loses nothing already computed); this function writes no file. Level scans are registered
    before tilted ones (their partners must be placed first).

    ``beside``: further links (not in the project yet) that the thread preparing scans ahead
    registers once its preparations are done, while the links to the centre run (a survey's
    further pairs); the caller finishes the queue, then lets the scans' ICP search structures go
    (``scans.prepared.release(("icp_reference",))``), which this function does otherwise.

    Returns a :class:`PlotOutcome`; the link results and poses are in the project.
    """
    default_links(project)
    scans = scans or ScanCache(project)
    _readable_centre(project)
    step = Progress(progress, cancel=cancel)
    order = [s for s in project.scans if s.name != project.centre and not s.tilted] + [
        s for s in project.scans if s.tilted and s.name != project.centre
    ]
    outcome = PlotOutcome(scans={project.centre: "centre"})
    ahead = _PrepareAhead.start(project, order, scans, rerun=rerun, cancel=cancel, beside=beside)
    try:
        _register_links(
            project,
            order,
            scans,
            outcome,
            step,
            ahead,
            rerun=rerun,
            cancel=cancel,
            on_link=on_link,
            on_link_done=on_link_done,
        )
    except BaseException:
        if ahead is not None:  # cancelled or failed: a preparation under way ends in its daemon thread
            ahead.stop()
        raise
    if ahead is not None:
        # the links are done: the thread preparing ahead ends before the run goes on, so nothing of
        # this run still imports or reads while the caller carries on (an import of open3d walks
        # sys.modules and breaks when another thread imports at the same time)
        ahead.stop(wait=beside is None)
    extra = [link for link in project.links if link.extra and (rerun or link.result is None)]
    for link in extra:
        link.result = _run_link(project, link, scans, Progress(None, cancel=cancel), cancel)
        if on_link_done is not None:
            on_link_done(project)
    if beside is None:  # the links are done: their ICP search structures go (the caller's queue still needs them)
        scans.prepared.release(("icp_reference",))
    if not any(link.ok for link in project.links) and project.centre not in scans._frames:
        try:  # the centre's header looked right but no link could read it: never "ok" unread
            scans.frame(project.centre)
        except (ScanReadError, ScanDataError) as exc:
            outcome.scans[project.centre] = "failed"
            outcome.reasons[project.centre] = str(exc)
    # a scan whose chain to the centre is broken has no pose even if its own link worked
    poses = project.chained_poses()
    for name, pose in poses.items():
        if pose is None and outcome.scans.get(name) == "ok":
            outcome.scans[name] = "failed"
            outcome.reasons[name] = "its reference scan could not be registered"
    step(1.0, "done")
    return outcome


def _unreadable(path: Path) -> Optional[str]:
    """Why a scan file cannot be read, from what is known without reading its points (missing,
    empty, content not of its format, a damaged or truncated LAS/LAZ header); None when nothing
    is known against it (reading it may still fail: its links then say why)."""
    from ..io.base import check_readable
    from ..io.las import check_las_header
    from ..io.sniff import detect_format

    try:
        check_readable(path)
        if detect_format(Path(path)) == "las" and check_las_header(Path(path))[0] == 0:
            return f"{path}: contains no points"
    except (ScanReadError, ScanDataError) as exc:
        return str(exc)
    return None


def _readable_centre(project: Project) -> None:
    """The centre scan must be readable: an unreadable one (missing, corrupt, empty) would be
    reported "ok" with an identity matrix while every scan fails onto it. Then the first level
    scan with nothing known against it becomes the centre, the links to the old centre are made
    to the new one, and the unreadable scan gets a link of its own (which fails with the reason).
    Without such a scan: DataError with the reason. Known from the files' headers, no points
    read (:func:`_unreadable`)."""
    old = project.centre
    reason = _unreadable(project.scan(old).path)
    if reason is None:
        return
    new = next(
        (
            s.name
            for s in sorted(project.scans, key=lambda s: s.tilted)
            if s.name != old and _unreadable(s.path) is None
        ),
        None,
    )
    if new is None:
        raise DataError(f"no scan of the plot can be read (the centre scan {old}: {reason})")
    log.warning("the centre scan %s cannot be read (%s): %s is the centre instead", old, reason, new)
    project.set_centre(new)
    for link in list(project.links):
        if link.reference == old and not link.extra and link.method != "manual":
            project.set_link(link.moving, new, vop_radius_m=link.vop_radius_m, slice_offsets_m=link.slice_offsets_m)
    if project.link_of(old) is None:
        project.set_link(old, new)


def _register_links(
    project: Project,
    order: list[ScanEntry],
    scans: ScanCache,
    outcome: PlotOutcome,
    step: Progress,
    ahead: Optional["_PrepareAhead"],
    *,
    rerun: bool,
    cancel: Optional[CancelToken],
    on_link: Optional[Callable[[Link], None]],
    on_link_done: Optional[Callable[[Project], None]],
) -> None:
    """The links of :func:`register_project`, one after the other in ``order``."""
    for k, entry in enumerate(order):
        if ahead is not None:
            ahead.at(k)
        sub = step.sub(k / max(len(order), 1), (k + 1) / max(len(order), 1))
        link = project.link_of(entry.name)
        if link.ok and not rerun:
            outcome.scans[entry.name] = "ok"
            continue
        sub(0.0, f"registering {entry.name}")
        if entry.tilted and not entry.level_partner:
            link = _register_tilted_without_partner(project, entry, scans, sub, cancel)
        else:
            link.result = _run_link(project, link, scans, sub.sub(0.0, 0.5), cancel)
            if not link.ok:
                link = _retry(project, entry, link, scans, sub.sub(0.5, 1.0), cancel)
        outcome.scans[entry.name] = "ok" if link.ok else "failed"
        if not link.ok:
            outcome.reasons[entry.name] = link.result.get("reason", "") if link.result is not None else "not run"
            log.warning("%s could not be registered: %s", entry.name, outcome.reasons[entry.name])
        project.adjustment = None
        if on_link_done is not None:
            on_link_done(project)
        if on_link is not None:
            on_link(link)


def small_scans(project: Project, scans: ScanCache, names: list[str]) -> bool:
    """Whether the scans ``names`` are small enough for two of them to be read, prepared or
    registered at once and for all of them to stay prepared: LAS/LAZ files (their point counts
    known from the headers) of at most :data:`~forestreg.engine.tls.pair.SEQUENTIAL_PREPARE_POINTS`
    points each, whose preparations fit the cache's budget together. Larger plots are worked one
    scan and one link at a time (their memory stays within what the caches allow)."""
    points = [_file_scan_bytes(project.scan(name).path) // _FILE_BYTES_PER_POINT for name in dict.fromkeys(names)]
    return (
        bool(points)
        and min(points) > 0
        and max(points) <= SEQUENTIAL_PREPARE_POINTS
        and sum(points) * PREPARED_BYTES_PER_POINT <= scans.prepared.max_bytes
    )


class LinkQueue:
    """Links (further pairs of a survey) registered by whichever thread is free: the thread that
    prepares scans ahead, once its preparations are done (beside the links to the centre), and the
    calling thread after them (:meth:`finish`). Two links running at once have different
    references where the queue allows (each builds its reference's ICP search structures). Each
    link's result is what it would be run alone (a link depends only on its two prepared scans);
    the project is not saved from here (the caller saves)."""

    def __init__(self, project: Project, links: list[Link], scans: ScanCache, cancel: Optional[CancelToken]) -> None:
        self.project, self.links, self._scans, self._cancel = project, list(links), scans, cancel
        self._waiting = list(links)
        self._running: list[Link] = []
        self._helpers = 0  # threads in run()
        self._closed = False
        self._changed = threading.Condition()

    def _take(self, prepared_only: bool) -> Optional[Link]:
        with self._changed:
            if self._closed or (self._cancel is not None and self._cancel.cancelled):
                return None
            ready = [
                link
                for link in self._waiting
                if not prepared_only
                or all(
                    self._scans.is_prepared(name, link.params(self.project.params))
                    for name in (link.reference, link.moving)
                )
            ]
            busy = {link.reference for link in self._running}
            link = next((x for x in ready if x.reference not in busy), ready[0] if ready else None)
            if link is not None:
                self._waiting = [x for x in self._waiting if x is not link]
                self._running.append(link)
            return link

    def _done(self, link: Link) -> None:
        with self._changed:
            self._running = [x for x in self._running if x is not link]
            self._changed.notify_all()

    def run(self, prepared_only: bool = False) -> None:
        """Register waiting links until none is left (with ``prepared_only``, only links whose
        two scans are kept prepared: a thread beside the links to the centre reads no scan)."""
        with self._changed:
            self._helpers += 1
        try:
            while (link := self._take(prepared_only)) is not None:
                try:
                    link.result = _run_link(
                        self.project, link, self._scans, Progress(None, cancel=self._cancel), self._cancel
                    )
                except Exception as exc:  # cancelled, or an error the calling thread meets again and reports
                    log.debug("%s onto %s left to the calling thread: %s", link.moving, link.reference, exc)
                    return
                finally:
                    self._done(link)
        finally:
            with self._changed:
                self._helpers -= 1

    def discard(self, link: Link) -> None:
        """Do not register ``link`` (if it has not started)."""
        with self._changed:
            self._waiting = [x for x in self._waiting if x is not link]

    def close(self) -> None:
        """Start no further link (one running finishes)."""
        with self._changed:
            self._closed = True
            self._changed.notify_all()

    def finish(self, step: Progress, after: Optional[Callable[[], None]] = None) -> None:
        """Register the links still waiting in this thread and one more (the thread already serving
        the queue, else one started here), then wait for those running in others;
        ``step`` advances and ``after`` (e.g. saving the project) is called as links end here. A
        link whose thread failed (cancelled) is left without a result, for the caller."""
        total = len(self.links)
        with self._changed:
            helped = self._helpers > 0
        if not helped and len(self._waiting) > 1:  # no other thread serves the queue: start one
            threading.Thread(target=self.run, name="forestreg-pair", daemon=True).start()

        def ended() -> int:
            return sum(link.result is not None for link in self.links)

        step(ended() / max(total, 1), f"registering {total} further pairs, two at a time")
        while (link := self._take(False)) is not None:
            try:
                link.result = _run_link(
                    self.project, link, self._scans, Progress(None, cancel=self._cancel), self._cancel
                )
            finally:
                self._done(link)
            step(
                ended() / max(total, 1),
                f"registered further pair {ended()} of {total}: {link.moving} onto {link.reference}",
            )
            if after is not None:
                after()
        with self._changed:
            while self._running:
                self._changed.wait()
        if after is not None:
            after()
        step(1.0, f"registered {ended()} further pairs")


class _PrepareAhead:
    """Reads and prepares, in a background thread, the scans of the next link while a link is
    registered (a link's coarse matching and ICP leave a core free; reading and preparing the next
    scan fills it), one link ahead: the preparations are kept by the :class:`ScanCache`, where the
    next link finds them. Only for plots of :func:`small_scans`, and only when the process may use
    two cores or more (:func:`~forestreg.engine.core.jit.worker_count`: a batch running each plot
    on one thread gets one core's work from it); larger plots read and prepare one scan at a time. A scan that cannot be read or prepared here is left to its link, which reads it
    again and says why."""

    def __init__(
        self,
        scans: ScanCache,
        plan: list[tuple[int, str, Any]],
        cancel: Optional[CancelToken],
        beside: Optional[LinkQueue],
    ) -> None:
        self._scans, self._plan, self._cancel, self._beside = scans, plan, cancel, beside
        self._current = -1
        self._stopped = False
        self._wake = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="forestreg-prepare-ahead", daemon=True)

    @classmethod
    def start(
        cls,
        project: Project,
        order: list[ScanEntry],
        scans: ScanCache,
        *,
        rerun: bool,
        cancel: Optional[CancelToken],
        beside: Optional[LinkQueue] = None,
    ) -> Optional["_PrepareAhead"]:
        """The preparer for the links of ``order`` that will run, started; None when the plot is not
        eligible (see the class). With ``beside``, once its preparations are done the thread
        registers the queue's links whose scans are prepared."""
        plan: list[tuple[int, str, Any]] = []
        seen: set = set()
        for k, entry in enumerate(order):
            link = project.link_of(entry.name)
            if (
                link is None
                or (link.ok and not rerun)
                or link.method == "manual"
                or (entry.tilted and not entry.level_partner)
            ):
                continue
            params = link.params(project.params)
            if not plan:  # the first link prepares its reference itself, while its moving scan is prepared here
                seen.add((link.reference, params))
            for name in (link.reference, link.moving):
                if (name, params) not in seen:
                    seen.add((name, params))
                    plan.append((k, name, params))
        from ..core.jit import worker_count

        if not plan or not scans.small or worker_count() < 2:  # one core (a batch's one thread a plot): nothing is free
            return None
        ahead = cls(scans, plan, cancel, beside)
        ahead._thread.start()
        return ahead

    def at(self, k: int) -> None:
        """The links have reached ``order[k]``: the scans of link ``k + 1`` may be prepared."""
        with self._wake:
            self._current = k
            self._wake.notify_all()

    def stop(self, wait: bool = False) -> None:
        """Prepare nothing more; ``wait``: until a preparation under way has finished (else it
        finishes in its daemon thread)."""
        with self._wake:
            self._stopped = True
            self._wake.notify_all()
        if wait and self._thread is not threading.current_thread():
            self._thread.join()

    def _run(self) -> None:
        for k, name, params in self._plan:
            with self._wake:
                self._wake.wait_for(lambda: self._stopped or k <= self._current + 1)
                if self._stopped or (self._cancel is not None and self._cancel.cancelled):
                    return
            try:
                self._scans.for_link(name, params)
            except Exception as exc:  # the link reads the scan again and reports why
                log.debug("%s was not prepared ahead: %s", name, exc)
        if self._beside is not None:
            self._beside.run(prepared_only=True)  # (errors are left to the calling thread)


def _run_link(
    project: Project, link: Link, scans: ScanCache, progress: Progress, cancel: Optional[CancelToken]
) -> LinkResult:
    """Run one link (auto or manual) and return its typed result; an unusable scan or data that
    do not allow it give a "failed" result with the reason, not an exception."""
    reading = link.reference
    try:
        if link.method == "manual":
            reference = scans(link.reference)
            reading = link.moving
            moving = scans(link.moving)
        else:
            # the reference prepared first and held as a stand-in without points, then the moving
            # scan (a stand-in too when its preparation is kept): one scan's points at a time
            params = link.params(project.params)
            progress(0.0, "preparing both scans")  # (or waiting for the thread preparing them ahead)
            reference = scans.for_link(link.reference, params)
            reading = link.moving
            moving = scans.for_link(link.moving, params, prepare=False)
    except (ScanReadError, ScanDataError, DataError) as exc:
        # one unusable scan (unreadable, no scanner position to be found) fails its links, not the
        # plot; a link that fails on its reference says so (the reference's own entry has the reason)
        reason = str(exc)
        if reading == link.reference:  # the moving scan's own fault first, when its header shows one
            own = _unreadable(project.scan(link.moving).path)
            reason = own or f"its reference scan {link.reference} cannot be used ({exc})"
        return LinkResult.from_dict(
            {"status": "failed", "reason": reason, "matrix": None, "reference": link.reference, "moving": link.moving}
        )
    if link.method == "manual":
        from .manual import register_manual

        result = register_manual(
            reference,
            moving,
            project.scan(link.reference).targets,
            project.scan(link.moving).targets,
            link.params(project.params),
            progress=progress,
            cancel=cancel,
        )
    else:
        prior = _link_prior(project, link, reference, moving)
        try:
            result = register(
                reference,
                moving,
                link.params(project.params),
                progress=progress,
                cancel=cancel,
                prior=prior,
                prepared=scans.prepared,
            )
        except DataError as exc:  # e.g. no points near a georeferenced scan's assumed scanner
            return LinkResult.from_dict({"status": "failed", "reason": str(exc), "matrix": None})
        finally:
            if not scans.small:  # the ICP search structures: ~30 bytes a point of each scan
                scans.prepared.release(("icp_reference",))
    return LinkResult.from_dict(result.to_dict())


def informative_priors(project: Project) -> bool:
    """False when every scan's prior pose is the same matrix (e.g. an E57 whose scans all carry
    identity poses: they are not placed in a common frame, so the poses say nothing)."""
    priors = [np.asarray(s.prior_pose) for s in project.scans if s.prior_pose is not None]
    return len(priors) >= 2 and not all(np.allclose(p, priors[0]) for p in priors[1:])


def _link_prior(project: Project, link: Link, reference: Scan, moving: Scan) -> Optional[np.ndarray]:
    """A rough moving-file -> reference-file matrix from the scans' prior poses (E57/SOP, a
    positions/headings file), or identity when both files share a georeferenced frame; None
    otherwise. Used only to decide between solutions that pass every check."""
    a, b = project.scan(link.moving).prior_pose, project.scan(link.reference).prior_pose
    if a is not None and b is not None and informative_priors(project):
        return np.linalg.inv(np.asarray(b)) @ np.asarray(a)
    if np.abs(reference.origin_shift).max() > 0.0 and np.abs(moving.origin_shift).max() > 0.0:
        return np.eye(4)
    return None


def _retry(
    project: Project,
    entry: ScanEntry,
    failed: Link,
    scans: ScanCache,
    progress: Progress,
    cancel: Optional[CancelToken],
) -> Link:
    """Try the failed scan against the scans already registered, nearest to its first reference
    first; keep the first success (the failed attempt is recorded in the link)."""
    poses = project.chained_poses()
    first = poses.get(failed.reference)
    candidates = [n for n, p in poses.items() if p is not None and n not in (entry.name, failed.reference)]
    if first is not None:
        candidates.sort(key=lambda n: float(np.linalg.norm(poses[n][:3, 3] - first[:3, 3])))
    tried = [
        {
            "reference": failed.reference,
            "reason": (failed.result if failed.result is not None else {}).get("reason", ""),
        }
    ]
    for k, name in enumerate(candidates):
        link = Link(
            moving=entry.name,
            reference=name,
            method=failed.method,
            vop_radius_m=failed.vop_radius_m,
            slice_offsets_m=failed.slice_offsets_m,
        )
        link.result = _run_link(
            project, link, scans, progress.sub(k / len(candidates), (k + 1) / len(candidates)), cancel
        )
        if link.ok:
            link.result = link.result.replace(retried_after=tried)
            project.replace_link(failed, link)
            log.info("%s registered onto %s after %d failed attempt(s)", entry.name, name, len(tried))
            return link
        tried.append({"reference": name, "reason": link.result.get("reason", "")})
    failed.result = dict(failed.result if failed.result is not None else {}, retried=tried[1:])
    return failed


def _register_tilted_without_partner(
    project: Project, entry: ScanEntry, scans: ScanCache, progress: Progress, cancel: Optional[CancelToken]
) -> Link:
    """A tilted scan whose level partner is not named: register it to every registered level scan
    (D_r ``tilted_partner_vop_radius_m``) and take the success whose scanner lies closest (the
    partner stands at the same spot)."""
    poses = project.chained_poses()
    level = [s.name for s in project.scans if not s.tilted and poses.get(s.name) is not None]
    best: Optional[Link] = None
    last: Optional[Link] = None
    for k, name in enumerate(level):
        link = Link(moving=entry.name, reference=name, vop_radius_m=project.params.tilted_partner_vop_radius_m)
        link.result = _run_link(project, link, scans, progress.sub(k / len(level), (k + 1) / len(level)), cancel)
        last = link
        if link.ok and (best is None or np.linalg.norm(link.matrix[:3, 3]) < np.linalg.norm(best.matrix[:3, 3])):
            best = link
    current = project.link_of(entry.name)
    chosen = best or last or current
    if best is not None:
        entry.level_partner = best.reference
    project.replace_link(current, chosen)
    return chosen


def link_residuals(project: Project, poses: dict[str, Optional[np.ndarray]]) -> list[dict[str, Any]]:
    """For every successful link, how far the poses disagree with it: rotation (deg) and
    translation (m, at the moving scanner) between the link's matrix and ``inv(pose_ref) @ pose_mov``."""
    rows = []
    for link in project.links:
        m = link.matrix
        pr, pm = poses.get(link.reference), poses.get(link.moving)
        if m is None or pr is None or pm is None:
            continue
        rot, trans = rigid_errors(np.linalg.inv(pr) @ pm, m)
        rows.append({"moving": link.moving, "reference": link.reference, "rotation_deg": rot, "translation_m": trans})
    return rows


def adjust_poses(
    project: Project, scans: Optional[ScanCache] = None, *, voxel_m: float = 0.1, max_distance_m: float = 0.1
) -> Optional[dict[str, Any]]:
    """Global adjustment: where successful links close loops (more links than a tree needs), a
    pose graph (open3d, Levenberg-Marquardt, the centre scan fixed) spreads the disagreement over
    the links. Each link is weighted by the information matrix of its overlap.

    Stores and returns ``{"poses": {name: 4x4 | None}, "links": [per-link residuals before and
    after]}`` in ``project.adjustment``; returns None (and clears it) where there is no loop.
    """
    chained = project.chained_poses()
    names = [s.name for s in project.scans if chained.get(s.name) is not None]
    links = [link for link in project.links if link.ok and link.moving in names and link.reference in names]
    if len(links) <= len(names) - 1:
        project.adjustment = None
        return None
    o3d = import_open3d()
    scans = scans or ScanCache(project)
    index = {n: i for i, n in enumerate(names)}
    reg = o3d.pipelines.registration
    graph = reg.PoseGraph()
    for n in names:
        graph.nodes.append(reg.PoseGraphNode(chained[n]))
    clouds: dict[str, Any] = {}

    def cloud(name: str):
        if name not in clouds:
            scan = scans(name)
            pts = scan.file_points
            pts = pts[np.sum((pts - scan.scanner_position_file) ** 2, axis=1) <= project.params.max_range_m**2]
            clouds[name] = voxel_downsample(pts - chained[project.centre][:3, 3], voxel_m)
        return clouds[name]

    for link in links:
        information = information_matrix(cloud(link.moving), cloud(link.reference), max_distance_m, link.matrix)
        graph.edges.append(
            reg.PoseGraphEdge(index[link.moving], index[link.reference], link.matrix, information, uncertain=link.extra)
        )
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=max_distance_m, edge_prune_threshold=0.25, reference_node=index[project.centre]
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(
            graph, reg.GlobalOptimizationLevenbergMarquardt(), reg.GlobalOptimizationConvergenceCriteria(), option
        )
    adjusted: dict[str, Optional[np.ndarray]] = {s.name: None for s in project.scans}
    centre_inv = np.linalg.inv(np.asarray(graph.nodes[index[project.centre]].pose))
    for n in names:
        adjusted[n] = centre_inv @ np.asarray(graph.nodes[index[n]].pose)
    before = {(r["moving"], r["reference"]): r for r in link_residuals(project, chained)}
    rows = []
    for r in link_residuals(project, adjusted):
        b = before.get((r["moving"], r["reference"]), {})
        rows.append(
            {
                "moving": r["moving"],
                "reference": r["reference"],
                "before": {"rotation_deg": b.get("rotation_deg"), "translation_m": b.get("translation_m")},
                "after": {"rotation_deg": r["rotation_deg"], "translation_m": r["translation_m"]},
            }
        )
    project.adjustment = {"poses": {k: (None if v is None else v.tolist()) for k, v in adjusted.items()}, "links": rows}
    return project.adjustment


def information_matrix(
    moving: np.ndarray, reference: np.ndarray, max_distance_m: float, matrix: np.ndarray
) -> np.ndarray:
    """The 6 x 6 information matrix of a link (rotation first, then translation; Choi et al.
    2015, as open3d's ``get_information_matrix_from_point_clouds``): each ``moving`` point moved by
    ``matrix`` and its nearest ``reference`` point within ``max_distance_m`` (both (N, 3), metres)
    adds ``G.T @ G`` for ``G = [-[q]x | I]`` at that reference point ``q``. Summed in a fixed order
    (open3d sums per thread and adds the threads' sums as they finish: its result changed in the
    last bits from run to run)."""
    from scipy.spatial import cKDTree

    moved = apply_transform(np.asarray(matrix), np.asarray(moving, dtype=np.float64))
    if len(moved) == 0 or len(reference) == 0:
        return np.zeros((6, 6))
    distance, index = cKDTree(np.asarray(reference, dtype=np.float64)).query(
        moved, distance_upper_bound=float(max_distance_m)
    )
    q = np.asarray(reference, dtype=np.float64)[index[np.isfinite(distance)]]
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    zero, one = np.zeros(len(q)), np.ones(len(q))
    g = np.concatenate(
        [
            np.stack([zero, z, -y, one, zero, zero], axis=1),
            np.stack([-z, zero, x, zero, one, zero], axis=1),
            np.stack([y, -x, zero, zero, zero, one], axis=1),
        ]
    )
    return np.einsum("ni,nj->ij", g, g)


def poses_document(project: Project, outcome: Optional[PlotOutcome] = None) -> tuple[dict[str, Any], dict[str, str]]:
    """The body of ``poses.json`` (``{"frame": centre, "scans": {name: {"status", "matrix"}}}``,
    each matrix mapping that scan's file coordinates into the centre scan's) and the text of one
    ``<scan>.transform.txt`` per registered scan (scan -> text); written by
    :func:`forestreg.engine.io.results.write_poses_files`."""
    poses = project.poses()
    body: dict[str, Any] = {
        "frame": project.centre,
        "convention": "p_centre = matrix @ p_scan (file coordinates)",
        "scans": {},
    }
    transforms: dict[str, str] = {}
    for s in project.scans:
        pose = poses.get(s.name)
        if outcome is not None and outcome.scans.get(s.name) == "failed":
            pose = None  # e.g. a centre scan that could not be read: no identity matrix for it
        entry: dict[str, Any] = {
            "status": "ok" if pose is not None else "failed",
            "matrix": None if pose is None else pose.tolist(),
        }
        if pose is None and outcome is not None and s.name in outcome.reasons:
            entry["reason"] = outcome.reasons[s.name]
        link = project.link_of(s.name)
        if link is not None:
            entry["reference"] = link.reference
        body["scans"][s.name] = entry
        if pose is not None:
            transforms[s.name] = format_matrix(pose)
    uncertainty = pose_uncertainty(project)
    quality = (project.adjustment or {}).get("quality") or {}
    for name, entry in body["scans"].items():
        if entry["status"] == "ok":
            entry["uncertainty"] = uncertainty.get(name)
        if name in quality:
            entry["quality"] = quality[name]
    # always present (None without loops), so readers never meet a missing key
    body["adjustment"] = (project.adjustment or {}).get("links")
    if project.adjustment and project.adjustment.get("method") == "survey":
        body["dropped_links"] = project.adjustment.get("dropped", [])
        body["loops"] = project.adjustment.get("triangles", [])
        body["uncertainty_inflation"] = project.adjustment.get("uncertainty_inflation")
    return body, transforms


def pose_uncertainty(project: Project) -> dict[str, Optional[dict[str, float]]]:
    """1-sigma uncertainty (``translation_m``, ``rotation_deg``) of every registered pose relative
    to the frame scan: the survey solution's where there is one, else propagated along the links
    from each pair's own uncertainty (see :mod:`~forestreg.engine.tls.uncertainty`)."""
    from .uncertainty import propagate_uncertainty

    stored = (project.adjustment or {}).get("uncertainty")
    if stored:
        return dict(stored)
    poses = project.poses()
    positions = {n: p[:3, 3] for n, p in poses.items() if p is not None}
    rows = []
    for link in project.links:
        u = (link.result if link.result is not None else {}).get("uncertainty") or {}
        if link.ok and link.moving in positions and link.reference in positions:
            rows.append(
                {
                    "moving": link.moving,
                    "reference": link.reference,
                    "translation_m": u.get("translation_m"),
                    "rotation_deg": u.get("rotation_deg"),
                }
            )
    if project.centre is None:
        return {}
    found = propagate_uncertainty(project.centre, positions, rows)
    return {n: found.get(n) for n in positions}


def merged_chunks(
    project: Project, path: str | Path, scans: Optional[ScanCache] = None
) -> tuple[Any, tuple[np.ndarray, np.ndarray], bool]:
    """Every registered scan in the centre scan's file coordinates, for one point file with a
    ``scan_id`` per point (the scan's index in the project): the chunks ``(points, intensity,
    scan_id)`` (a generator: one scan read at a time, so a plot larger than memory can be
    merged), the bounds of all points and whether every scan has intensities. For LAS/LAZ/COPC
    (``path``'s suffix) a scan goes in blocks of :data:`MERGE_BLOCK_POINTS`, its intensities mapped
    to uint16 once for the whole scan (as the writer maps each chunk); other formats take each
    scan whole. Written by :func:`~forestreg.engine.io.write_point_chunks`."""
    scans = scans or ScanCache(project)
    poses = project.poses()
    placed = [(k, s.name, poses[s.name]) for k, s in enumerate(project.scans) if poses.get(s.name) is not None]
    if not placed:
        raise DataError("no scan is registered: nothing to merge")
    scans.clear()  # merging reads each scan once: kept scans and preparations (0.8 / 0.5 GB each at 30 M points) go
    corners = []
    for _, name, pose in placed:
        lo, hi = scans.bounds(name)
        box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        corners.append(apply_transform(pose, box))
    corners = np.vstack(corners)
    margin = 1.0  # metres: header bounds are rounded; the written header has the exact ones
    streamed = Path(path).suffix.lower() in (".las", ".laz")

    def chunks():
        for k, name, pose in placed:
            scan = scans(name, keep=False)  # each scan is merged once: not kept
            if not streamed:
                yield apply_transform(pose, scan.file_points), scan.intensity, np.full(len(scan), k, dtype=np.uint16)
                continue
            intensity = None if scan.intensity is None else intensity_to_uint16(scan.intensity)
            for a in range(0, len(scan), MERGE_BLOCK_POINTS):
                b = min(len(scan), a + MERGE_BLOCK_POINTS)
                moved = apply_transform(pose, scan.points[a:b] + scan.origin_shift)
                yield moved, None if intensity is None else intensity[a:b], np.full(b - a, k, dtype=np.uint16)
            del scan, intensity

    with_intensity = all(_has_intensity(scans, project.scan(name)) for _, name, _ in placed)
    return chunks(), (corners.min(axis=0) - margin, corners.max(axis=0) + margin), with_intensity


#: Points of a scan transformed and handed to the writer at a time by :func:`merged_chunks`.
MERGE_BLOCK_POINTS = 2_000_000


def _has_intensity(scans: ScanCache, entry: ScanEntry) -> bool:
    """Whether a scan has intensities (a LAS/LAZ always has the field; other formats: read it)."""
    if entry.path.suffix.lower() in (".las", ".laz"):
        return True
    return scans(entry.name).intensity is not None


def project_from_e57(path: str | Path, *, name: Optional[str] = None) -> Project:
    """A project with one scan per data3D entry of a multi-scan E57 file; each entry's pose is kept
    as a prior (``ScanEntry.prior_pose``) and the first scan is the centre."""
    from ..io import read_scans

    source = Path(path).resolve()
    project = Project(name=name or source.stem)
    for k, scan in enumerate(read_scans(source)):
        label = scan.name if scan.name and scan.name != source.stem else f"{source.stem}_{k:02d}"
        project.add_scan(
            source, name=label, scan_index=k, prior_pose=None if scan.pose is None else np.array(scan.pose)
        )
    return project


def registered_scans(project: Project, scans: Optional[ScanCache] = None) -> list[tuple[str, Any, np.ndarray]]:
    """``(name, scan, pose)`` of every registered scan, the pose mapping its own file coordinates
    into the centre scan's (scans read on demand: a list of names with a reader behind)."""
    scans = scans or ScanCache(project)
    poses = project.poses()
    chosen = [s.name for s in project.scans if poses.get(s.name) is not None]
    if not chosen:
        raise DataError("no scan is registered: nothing to write")
    return [(n, _Lazy(scans, n), poses[n]) for n in chosen]


class _Lazy:
    """A scan of a :class:`ScanCache`, read when asked for (``scan()``)."""

    def __init__(self, scans: ScanCache, name: str) -> None:
        self.scans, self.name = scans, name

    def __call__(self) -> Scan:
        return self.scans(self.name)


def add_neighbour_links(project: Project, max_distance_m: float) -> list[Link]:
    """Add an extra link between every two registered scans (neither the centre) whose scanners
    stand within ``max_distance_m`` of each other and are not linked yet: loops for
    :func:`adjust_poses`. Run them with :func:`register_project`. Returns the new links."""
    poses = project.chained_poses()
    linked = {frozenset((link.moving, link.reference)) for link in project.links}
    placed = [s.name for s in project.scans if s.name != project.centre and poses.get(s.name) is not None]
    added = []
    for i, a in enumerate(placed):
        for b in placed[i + 1 :]:
            if frozenset((a, b)) in linked:
                continue
            if np.linalg.norm(poses[a][:2, 3] - poses[b][:2, 3]) <= max_distance_m:
                added.append(project.add_link(b, a))
    return added
