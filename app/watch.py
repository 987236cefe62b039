"""Field registration: watch the folder a scanner's export fills and register each scan as it
arrives (``forestreg plot --watch FOLDER --out OUT``).

A file is taken in once it is complete: its size and modification time did not change between two
polls, and its content agrees with itself (a LAS/LAZ header's point data and, for LAZ, its chunk
table lie within the file; another format reads). A file still being written waits; a file that
is no scan is named once and ignored; a copy of a scan taken in already (the same content, by
SHA-256) is registered once.

Each scan taken in is registered by the plot's own engine path (:func:`~forestreg.engine.tls.plot.
register_project`: onto the centre scan - the first one, or ``centre`` - and, failing that, onto
the placed scans nearest it first), then the plot folder is written by :func:`~forestreg.app.plot.
run_plot`, so the poses after the last scan are those ``forestreg plot`` gives for the same scans
in the same order. A scan that does not link is set aside with the reason: "refused" when its trunk
shadows match no placed scan's beyond a chance match (a scan of another plot, or one taken too
far from every placed scan), "not linked" otherwise, with a position that would link
(:mod:`forestreg.app.plan`). Set-aside scans are tried again when a scan is placed whose trunk
shadows they share.

Each update of ``OUT`` is one transaction: every file is written into a temporary folder inside
``OUT`` first, then moved in by one rename each - the report, the transforms, ``project.json``,
``watch.json`` (the state of the watch: which files were taken in, their content hashes and
outcomes) and ``poses.json`` last. A watch stopped at any point (Ctrl-C, a kill) leaves the files
of the last update whole, and started again on the same folder and ``OUT`` it goes on from the
scans placed: none is lost or registered twice.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import struct
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

from .common import RunOutcome
from .plot import PoseSigma

log = logging.getLogger("forestreg")

#: The watch's state file in the plot folder.
WATCH_FILE = "watch.json"
WATCH_FORMAT = "forestreg-watch"
WATCH_VERSION = 1
#: What a file taken in became (``WatchEvent.status``) - placed: "centre", "linked"; set aside:
#: "not linked", "refused"; not taken in: "duplicate", "ignored"; still to come: "waiting".
PLACED, SET_ASIDE = ("centre", "linked"), ("not linked", "refused")


@dataclass(frozen=True)
class WatchEvent:
    """What happened to one file of the watched folder: ``status`` (see :data:`PLACED`,
    :data:`SET_ASIDE`, "duplicate", "ignored", "waiting"), the line printed for it (``message``),
    the scan it was registered onto, its pose's 1-sigma uncertainty relative to the centre scan,
    the scans placed and taken in so far (a duplicate and a file that is no scan are not taken in),
    the seconds from the file's completion to the plot folder's update, the reason it was not
    placed, the suggested position ``(x, y)`` that would link (centre scan's file coordinates, m),
    and the scan a duplicate repeats."""

    name: str
    status: str
    message: str
    reference: Optional[str] = None
    sigma: Optional[PoseSigma] = None
    placed: int = 0
    total: int = 0
    seconds: Optional[float] = None
    reason: str = ""
    advice: Optional[tuple] = None
    same_as: Optional[str] = None

    def to_dict(self) -> dict[str, Any]:
        """The JSON-lines event of ``--progress jsonl`` (``{"event": "scan", ...}``)."""
        sigma = (
            None
            if self.sigma is None
            else {"translation_m": self.sigma.translation_m, "rotation_deg": self.sigma.rotation_deg}
        )
        return {
            "event": "scan",
            "name": self.name,
            "status": self.status,
            "reference": self.reference,
            "sigma": sigma,
            "placed": self.placed,
            "total": self.total,
            "seconds": None if self.seconds is None else round(self.seconds, 3),
            "reason": self.reason,
            "advice": None if self.advice is None else [round(v, 2) for v in self.advice],
            "same_as": self.same_as,
            "message": self.message,
        }


@dataclass(frozen=True, eq=False)
class WatchRun(RunOutcome):
    """A watch that ended: ``placed`` and ``taken`` scans (names), those set aside with their
    reasons, whether it was stopped (Ctrl-C) rather than ending after ``until_scans``, and the
    events in order. Failed when a scan taken in was not placed."""

    placed: tuple = ()
    taken: tuple = ()
    aside: dict = field(default_factory=dict)
    stopped: bool = False
    events: tuple = ()
    resumed: int = 0


# ----------------------------------------------------------------------------- is a file complete?


@dataclass(frozen=True)
class FileCheck:
    """Whether a file is a complete scan: ``state`` "complete", "partial" (wait for the rest) or
    "not a scan", and why not."""

    state: str
    reason: str = ""


def check_scan_file(path: Path) -> FileCheck:
    """Whether the file ``path`` (whose size held still over two polls) is a complete scan: a
    LAS/LAZ whose header fits the file (the point records of a LAS, the chunk table of a LAZ lie
    within it), or a file of another point format that reads."""
    from ..engine.core.errors import ForestregError
    from ..engine.io import SUPPORTED_READ_SUFFIXES

    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        return FileCheck("partial", f"cannot be opened yet ({exc.strerror or exc})")
    suffix = path.suffix.lower()
    if head.startswith(b"LASF") or suffix in (".las", ".laz"):
        return _check_las(path)
    if suffix not in SUPPORTED_READ_SUFFIXES:
        return FileCheck("not a scan", f"not a point file ({path.suffix or 'no suffix'})")
    from ..engine.io import read_scan

    try:
        read_scan(path, with_intensity=False)
    except (ForestregError, OSError, ValueError, MemoryError) as exc:
        return FileCheck(
            "not a scan", f"cannot be read as a scan ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
        )
    return FileCheck("complete")


def _check_las(path: Path) -> FileCheck:
    from ..engine.core.errors import ScanReadError
    from ..engine.io.las import check_las_header

    try:
        count, compressed = check_las_header(path)
    except ScanReadError as exc:
        text = str(exc)
        if "truncated: " in text:  # what is missing (the point records, the LAZ chunk table)
            return FileCheck("partial", text.split("truncated: ", 1)[1])
        if "truncated" in text or "too short" in text:
            return FileCheck("partial", "the file is shorter than its header says")
        return FileCheck("not a scan", text.split(": ", 1)[-1])
    if count == 0:  # a writer that fills the count in at the end, or an empty scan
        return FileCheck("partial", "its header announces no points (yet)")
    if not compressed:
        return FileCheck("complete")
    with open(path, "rb") as f:
        f.seek(96)
        (offset,) = struct.unpack("<I", f.read(4))
        f.seek(offset)
        raw = f.read(8)
    if len(raw) < 8:
        return FileCheck("partial", "the compressed points have not arrived yet")
    (table,) = struct.unpack("<q", raw)  # (a table beyond the file's end: refused with the header)
    if table > 0 and not _chunk_table_reads(path, offset):
        return FileCheck("partial", "its chunk table has not arrived whole")
    if table <= 0 and not _all_points_read(path, count):  # no chunk table (yet): the points must all decode
        return FileCheck("partial", f"fewer than the {count:,} points its header announces decode")
    return FileCheck("complete")


def _all_points_read(path: Path, count: int) -> bool:
    """Whether all ``count`` points of a LAS/LAZ file decode."""
    try:
        import laspy

        with laspy.open(str(path)) as reader:
            n = sum(len(chunk) for chunk in reader.chunk_iterator(1_000_000))
    except Exception:  # laspy says only that the bytes ran out
        return False
    return n >= count


def _chunk_table_reads(path: Path, offset: int) -> bool:
    """Whether a LAZ file's chunk table (written last) reads whole; True when it cannot be
    checked here (no lazrs, no LASzip record: the read says what is wrong)."""
    try:
        import laspy
        import lazrs
    except ImportError:
        return True
    try:
        with laspy.open(str(path)) as reader:
            vlr = next((v for v in reader.header.vlrs if getattr(v, "record_id", None) == 22204), None)
        if vlr is None:
            return True
        with open(path, "rb") as f:
            f.seek(offset)
            lazrs.read_chunk_table(f, lazrs.LazVlr(vlr.record_data))
    except Exception:  # lazrs says only that the bytes ran out
        return False
    return True


def content_hash(path: Path) -> str:
    """The SHA-256 of a file's content (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


class FolderPoll:
    """The files of a folder between polls: a file is *settled* once its size and modification
    time are the same in two polls in a row. Hidden files (a copy tool's temporaries) and folders
    are not looked at."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self._seen: dict[str, tuple[int, int]] = {}

    def poll(self) -> list[Path]:
        """The settled files, oldest first (then by name)."""
        settled = []
        now: dict[str, tuple[int, int]] = {}
        try:
            entries = list(os.scandir(self.folder))
        except OSError as exc:
            log.warning("cannot list %s: %s", self.folder, exc)
            return []
        for e in entries:
            if e.name.startswith(".") or not e.is_file(follow_symlinks=True):
                continue
            try:
                st = e.stat(follow_symlinks=True)
            except OSError:
                continue
            now[e.name] = (st.st_size, st.st_mtime_ns)
            if self._seen.get(e.name) == now[e.name]:
                settled.append((st.st_mtime_ns, e.name))
        self._seen = now
        return [self.folder / name for _, name in sorted(settled)]

    def signature(self, name: str) -> Optional[tuple[int, int]]:
        """The (size, modification time in ns) of a file at the last poll."""
        return self._seen.get(name)


# ----------------------------------------------------------------------------- the watch


class Watch:
    """One watch of ``folder`` into the plot folder ``out`` (checked and locked by the caller:
    :func:`~forestreg.app.plot.plot_folder`). Call :meth:`step` once per poll."""

    def __init__(
        self,
        folder: Path,
        out: Path,
        params,
        *,
        centre: Optional[str] = None,
        scanner_params=None,
        plan_params=None,
        on_event: Optional[Callable[[WatchEvent], None]] = None,
        progress=None,
        cancel=None,
    ) -> None:
        from ..engine.tls.params import PlanParams
        from ..engine.tls.plot import ScanCache
        from ..engine.tls.project import Project

        self.folder, self.out = folder, out
        self.params, self.centre_name = params, centre
        self.plan_params = plan_params or PlanParams()
        self.on_event = on_event
        self.progress, self.cancel = progress, cancel
        self.project = Project(name=out.name, params=params)
        if scanner_params is not None:
            self.project.scanner_params = scanner_params
        self.cache = ScanCache(self.project, with_intensity=False)
        self.poller = FolderPoll(folder)
        #: file name -> {"sha256", "size", "mtime_ns", "status", "reason", "same_as", "reference"}
        self.files: dict[str, dict] = {}
        self.events: list[WatchEvent] = []
        self.waiting: list[Path] = []  # complete scans held until the centre scan arrives
        self._waiting_hash: dict[str, str] = {}  # their content hashes
        self._said: dict[str, tuple] = {}  # file -> (signature, what was said) of files not taken in
        self.resumed = 0

    # ------------------------------------------------------------------ counts

    def placed(self) -> list[str]:
        return [n for n, f in self.files.items() if f["status"] in PLACED]

    def taken(self) -> list[str]:
        return [n for n, f in self.files.items() if f["status"] in PLACED + SET_ASIDE]

    def _counted(self) -> list[str]:
        return [n for n, f in self.files.items() if f["status"] in PLACED + ("not linked",)]

    # ------------------------------------------------------------------ resuming

    def resume(self) -> int:
        """Take up the state a watch of the same folder left in ``out`` (its placed scans, set-aside
        scans and hashes); returns the scans placed before. A folder watched for another folder,
        with other registration settings or another centre is refused
        (:class:`~forestreg.engine.core.errors.UsageError`)."""
        from ..engine.core.atomic import TMP_PREFIX
        from ..engine.core.errors import UsageError
        from ..engine.tls.project import Project, ProjectFileError

        for leftover in self.out.glob(TMP_PREFIX + "watch.*"):
            shutil.rmtree(leftover, ignore_errors=True)
        state_file, project_file = self.out / WATCH_FILE, self.out / "project.json"
        if not state_file.is_file():
            if project_file.is_file():
                raise UsageError(f"--out {self.out} holds a plot registered without --watch: give a new folder")
            return 0
        try:
            state = json.loads(state_file.read_text(encoding="utf-8"))
            if state.get("format") != WATCH_FORMAT:
                raise ValueError("not a watch state")
        except (OSError, ValueError) as exc:
            raise UsageError(f"{state_file} cannot be read ({exc}): give a new --out") from exc
        if Path(state.get("folder", "")).resolve() != self.folder.resolve():
            raise UsageError(
                f"--out {self.out} holds the watch of another folder ({state.get('folder')}): give another --out"
            )
        if project_file.is_file():
            try:
                saved = Project.load(project_file)
            except ProjectFileError as exc:
                raise UsageError(str(exc)) from exc
            if saved.params.to_dict() != self.params.to_dict():
                raise UsageError(
                    f"--out {self.out} holds a plot registered with other settings (--dr, --dc, --dh or --params): "
                    "give the same settings or another --out"
                )
            if self.centre_name and saved.centre and saved.centre != self.centre_name:
                raise UsageError(
                    f"--out {self.out} holds a plot with the centre scan {saved.centre}, not {self.centre_name}"
                )
            self.project.scans, self.project.links, self.project.centre = saved.scans, saved.links, saved.centre
            self.project.scanner_params = saved.scanner_params
        self.files = {str(k): dict(v) for k, v in (state.get("files") or {}).items() if isinstance(v, dict)}
        poses = self.project.poses()
        for s in self.project.scans:  # placed after the state was last written (a kill in between)
            entry = self.files.setdefault(s.name, {})
            if entry.get("status") not in PLACED and poses.get(s.name) is not None:
                entry.update(
                    status="centre" if s.name == self.project.centre else "linked",
                    reference=None if s.name == self.project.centre else self.project.link_of(s.name).reference,
                )
                if s.path.is_file():
                    entry["sha256"] = content_hash(s.path)
        for name, entry in list(self.files.items()):  # a placed scan the project lost (never written): taken in again
            if entry.get("status") in PLACED and not self.project.has_scan(name):
                del self.files[name]
        self.resumed = len(self.placed())
        if self.resumed:
            self._publish()  # the files of the last update, whole and consistent
        return self.resumed

    # ------------------------------------------------------------------ one poll

    def step(self) -> list[WatchEvent]:
        """Look at the folder once and take in every scan that became complete; returns the events."""
        before = len(self.events)
        for path in self.poller.poll():
            self._consider(path)
        self._take_waiting()
        return self.events[before:]

    def _say_once(self, path: Path, what: tuple, event: WatchEvent) -> None:
        signature = self.poller.signature(path.name)
        if self._said.get(path.name) == (signature, what):
            return
        self._said[path.name] = (signature, what)
        self._emit(event)

    def _consider(self, path: Path) -> None:
        name = path.name
        known = self.files.get(name)
        signature = self.poller.signature(name)
        if (
            known is not None
            and known.get("status") in SET_ASIDE
            and signature is not None
            and (known.get("size"), known.get("mtime_ns")) != signature
        ):
            del self.files[name]  # set aside, then written again (a new export): taken in anew
            known = None
        if known is not None and known.get("status") in PLACED + SET_ASIDE:
            if known.get("size") is not None and signature is not None and known.get("size") != signature[0]:
                self._say_once(
                    path,
                    ("changed",),
                    WatchEvent(
                        name,
                        "ignored",
                        f"{name}: changed after it was taken in - the scan taken in stays; "
                        "copy the new content under a new name to register it",
                        reason="changed",
                    ),
                )
            return
        if (
            known is not None
            and known.get("status") in ("duplicate", "ignored")
            and known.get("size") == (signature or (None,))[0]
            and known.get("mtime_ns") == (signature or (None, None))[1]
        ):
            return
        if any(p.name == name for p in self.waiting):
            return
        check = check_scan_file(path)
        if check.state == "partial":
            self._say_once(
                path,
                ("partial", check.reason),
                WatchEvent(
                    name, "waiting", f"{name}: incomplete ({check.reason}) - waiting for the rest", reason=check.reason
                ),
            )
            return
        if check.state == "not a scan":
            self._record(name, signature, status="ignored", reason=check.reason)
            self._say_once(
                path,
                ("ignored", check.reason),
                WatchEvent(name, "ignored", f"{name}: not a scan - {check.reason}: ignored", reason=check.reason),
            )
            self._publish_state()
            return
        digest = content_hash(path)
        same = next(
            (n for n, f in self.files.items() if f.get("sha256") == digest and f.get("status") in PLACED + SET_ASIDE),
            None,
        )
        if same is None:
            same = next((p.name for p in self.waiting if self._waiting_hash.get(p.name) == digest), None)
        if same is not None:
            self._record(name, signature, status="duplicate", same_as=same, sha256=digest)
            self._emit(
                WatchEvent(name, "duplicate", f"{name}: the same content as {same} - registered once", same_as=same)
            )
            self._publish_state()
            return
        if self.project.centre is None and self.centre_name and name != self.centre_name:
            self.waiting.append(path)
            self._waiting_hash[name] = digest
            self._emit(
                WatchEvent(
                    name,
                    "waiting",
                    f"{name}: complete - waiting for the centre scan {self.centre_name}",
                    reason="no centre scan yet",
                )
            )
            return
        self._take(path, digest, signature)

    def _take_waiting(self) -> None:
        if self.project.centre is None or not self.waiting:
            return
        held, self.waiting = self.waiting, []
        for path in held:
            signature = self.poller.signature(path.name) or (path.stat().st_size, path.stat().st_mtime_ns)
            self._take(path, self._waiting_hash.pop(path.name, None) or content_hash(path), signature)

    def _record(self, name: str, signature, **entry) -> None:
        size, mtime = signature if signature is not None else (None, None)
        self.files[name] = {"size": size, "mtime_ns": mtime, **entry}

    # ------------------------------------------------------------------ taking a scan in

    def _take(self, path: Path, digest: str, signature) -> None:
        from ..engine.tls.plot import register_project

        started = time.perf_counter()
        name = path.name
        entry = self.project.add_scan(path)
        if entry.name != name:  # a file of the name of a scan the project holds (renamed and copied again)
            self.project.scans.remove(entry)
            self._record(
                name, signature, status="ignored", reason="a scan of this name was taken in already", sha256=digest
            )
            self._emit(WatchEvent(name, "ignored", f"{name}: a scan of this name was taken in already - ignored"))
            return
        if self.project.centre == name:
            self._record(name, signature, status="centre", sha256=digest)
            self._publish()
            self._emit(self._placed_event(name, "centre", started))
            return
        outcome = register_project(self.project, progress=self.progress, scans=self.cache, cancel=self.cancel)
        if outcome.scans.get(name) == "ok":
            self._record(
                name, signature, status="linked", sha256=digest, reference=self.project.link_of(name).reference
            )
            self._publish()
            self._emit(self._placed_event(name, "linked", started))
            self._retry_aside(name)
            return
        reason = outcome.reasons.get(name) or "not registered"
        self._set_aside(name, signature, digest, reason, started)

    def _set_aside(self, name: str, signature, digest: str, reason: str, started: float) -> None:
        """The scan ``name`` did not link: out of the project, kept aside with why and what to do."""
        status, line, advice, reason = self._why_not(name, reason)
        self._drop(name)
        self._record(name, signature, status=status, sha256=digest, reason=reason)
        self._publish()
        event = WatchEvent(
            name,
            status,
            f"{name}: {line}",
            placed=len(self.placed()),
            total=len(self._counted()),
            seconds=time.perf_counter() - started,
            reason=reason,
            advice=advice,
        )
        self._emit(event)

    def _drop(self, name: str) -> None:
        self.project.links = [link for link in self.project.links if link.moving != name and link.reference != name]
        self.project.scans = [s for s in self.project.scans if s.name != name]
        self.project.adjustment = None

    def _why_not(self, name: str, reason: str) -> tuple[str, str, Optional[tuple], str]:
        """(status, the line after the name, the suggested position, the reason) of a scan that
        did not link: "refused" when its trunk shadows match no placed scan's beyond a chance
        match, else "not linked" with a position that links to the scan it shares most with."""
        from ..engine.tls.plan import shadow_evidence

        placed = [n for n in self.placed() if self.project.has_scan(n)]
        try:
            moving = self.cache.prepared.get(self.cache.for_link(name, self.params), self.params)
        except Exception as exc:  # unreadable, no scanner position: the reason says it
            log.debug("%s: no trunk shadows to compare: %s", name, exc)
            return "refused", f"refused - {reason}", None, reason
        found = []
        for other in placed:
            ev = shadow_evidence(
                self.cache.prepared.get(self.cache.for_link(other, self.params), self.params), moving, self.params
            )
            found.append((ev.confident, ev.lead, ev.matched, other, ev))
        if not found:
            return "refused", f"refused - {reason}", None, reason
        confident, _, _, partner, ev = max(found, key=lambda x: x[:3])
        if not confident:
            why = (
                f"shares no trunk shadows with the {len(placed)} placed scan{'s' if len(placed) != 1 else ''} beyond a chance match "
                f"(best {ev.matched} with {partner}, another solution {ev.second})"
            )
            return (
                "refused",
                f"refused - {why}: a scan of another plot, or taken too far from every placed scan (it is tried again as scans are placed)",
                None,
                why,
            )
        link_reason = self._reason_onto(name, partner) or reason
        needed = self.params.min_matched
        why = f"shares {ev.matched} trunk shadows with {partner}" + (
            f" (needs {needed})" if ev.matched < needed else f", but {link_reason}"
        )
        advice = self._advice(partner)
        todo = (
            f": stand between them, near ({advice[0]:.1f}, {advice[1]:.1f})"
            if advice is not None
            else ": scan again between it and the placed scans"
        )
        return "not linked", f"not linked - {why}{todo}", advice, why

    def _reason_onto(self, name: str, reference: str) -> str:
        """Why the link of ``name`` onto ``reference`` failed, from its link's attempts."""
        link = self.project.link_of(name)
        if link is None or link.result is None:
            return ""
        if link.reference == reference:
            return str(link.result.reason or "")
        for tried in link.result.get("retried") or ():
            if isinstance(tried, dict) and tried.get("reference") == reference:
                return str(tried.get("reason") or "")
        return ""

    def _advice(self, partner: str) -> Optional[tuple]:
        """A position (x, y) that links to ``partner`` and sees the most stem area not seen yet."""
        from ..engine.tls.plan import placed_links, placed_views, plan_scans

        try:
            views = placed_views(
                self.project,
                self.cache,
                names=[n for n in self.placed() if self.project.has_scan(n)],
                cell_m=self.plan_params.ground_cell_m,
            )
            plan = plan_scans(
                views, self.plan_params, self.params, n=1, links_to=[partner], links=placed_links(self.project)
            )
        except Exception as exc:  # advice is a help, never the reason a watch stops
            log.debug("no advice for a scan next to %s: %s", partner, exc)
            return None
        return None if not plan.suggestions else (plan.suggestions[0].x, plan.suggestions[0].y)

    def _retry_aside(self, placed_now: str) -> None:
        """Scans set aside that share trunk shadows (beyond a chance match) with the scan just
        placed: registered again, onto it first; each one placed is tried in turn the same way."""
        from ..engine.tls.plan import shadow_evidence
        from ..engine.tls.plot import register_project

        found = []
        for name in [n for n, f in self.files.items() if f.get("status") in SET_ASIDE]:
            path = self.folder / name
            if not path.is_file():
                continue
            started = time.perf_counter()
            self.project.add_scan(path)
            try:
                ev = shadow_evidence(
                    self.cache.prepared.get(self.cache.for_link(placed_now, self.params), self.params),
                    self.cache.prepared.get(self.cache.for_link(name, self.params), self.params),
                    self.params,
                )
            except Exception as exc:  # unreadable now: it stays aside with its reason
                log.debug("%s not tried again: %s", name, exc)
                ev = None
            if ev is None or not ev.confident:
                self._drop(name)
                continue
            self.project.set_link(name, placed_now)
            outcome = register_project(self.project, progress=self.progress, scans=self.cache, cancel=self.cancel)
            if outcome.scans.get(name) != "ok":
                self._drop(name)
                continue
            self.files[name].update(status="linked", reference=self.project.link_of(name).reference, reason="")
            self._publish()
            self._emit(self._placed_event(name, "linked", started, after=placed_now))
            found.append(name)
        for name in found:
            self._retry_aside(name)

    def _placed_event(self, name: str, status: str, started: float, after: Optional[str] = None) -> WatchEvent:
        placed, total = len(self.placed()), len(self._counted())
        if status == "centre":
            line = f"{name}: centre (the plot's frame) - {placed} of {total} placed"
            return WatchEvent(name, status, line, placed=placed, total=total, seconds=time.perf_counter() - started)
        from .plot import pose_sigmas

        link = self.project.link_of(name)
        sigma = pose_sigmas(self.project).get(name)
        figures = (
            "ok"
            if sigma is None or not sigma.known
            else f"ok, {100 * sigma.translation_m:.1f} cm / {sigma.rotation_deg:.2f} deg"
        )
        later = f", once {after} was placed" if after else ""
        line = f"{name}: linked to {link.reference} ({figures}){later} - {placed} of {total} placed"
        return WatchEvent(
            name,
            status,
            line,
            reference=link.reference,
            sigma=sigma,
            placed=placed,
            total=total,
            seconds=time.perf_counter() - started,
        )

    def _emit(self, event: WatchEvent) -> None:
        self.events.append(event)
        if self.on_event is not None:
            self.on_event(event)

    # ------------------------------------------------------------------ writing OUT

    def _state(self) -> dict:
        return {
            "format": WATCH_FORMAT,
            "version": WATCH_VERSION,
            "folder": str(self.folder.resolve()),
            "centre": self.project.centre,
            "files": self.files,
        }

    def _publish_state(self) -> None:
        from ..engine.core.atomic import write_text_atomic

        write_text_atomic(self.out / WATCH_FILE, json.dumps(self._state(), indent=1) + "\n")

    def _publish(self) -> None:
        """Write the plot folder for the project as it is (the plot's products by
        :func:`~forestreg.app.plot.run_plot`, then ``project.json`` and ``watch.json``) into a
        temporary folder inside ``out`` and move each file in by one rename, ``poses.json`` last."""
        from ..engine.core.atomic import TMP_PREFIX
        from ..engine.core.jsonable import to_jsonable
        from .plot import run_plot

        tmp = Path(tempfile.mkdtemp(prefix=TMP_PREFIX + "watch.", dir=self.out))
        try:
            if self.project.scans:
                run_plot(self.project, tmp, scans=self.cache)
                text = json.dumps(to_jsonable(self.project.to_dict(relative_to=self.out.resolve())), indent=1) + "\n"
                (tmp / "project.json").write_text(text, encoding="utf-8")
            (tmp / WATCH_FILE).write_text(json.dumps(self._state(), indent=1) + "\n", encoding="utf-8")
            last = ("project.json", WATCH_FILE, "poses.json")
            files = sorted(
                (f for f in tmp.iterdir() if f.is_file()),
                key=lambda f: (last.index(f.name) if f.name in last else -1, f.name),
            )
            for f in files:
                os.replace(f, self.out / f.name)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


def watch_plot(
    folder,
    out,
    params,
    *,
    centre: Optional[str] = None,
    scanner_params=None,
    plan_params=None,
    poll_s: float = 1.0,
    until_scans: Optional[int] = None,
    on_event: Optional[Callable[[WatchEvent], None]] = None,
    progress=None,
    cancel=None,
    sleep: Callable[[float], None] = time.sleep,
    on_start: Optional[Callable[[int], None]] = None,
) -> WatchRun:
    """Watch ``folder`` and register each scan arriving there into the plot folder ``out`` (see
    the module docstring), polling every ``poll_s`` seconds, until ``until_scans`` scans have been
    taken in (placed or set aside; None: until Ctrl-C, which ends the watch normally with
    ``stopped``). ``on_event`` gets each :class:`WatchEvent` as it happens, ``on_start`` the
    number of scans a stopped watch placed before, once the folders are checked. The folder must
    exist; ``out`` is checked, locked and marked as a plot folder here."""
    from ..engine.core.errors import ScanReadError, UsageError
    from .plot import plot_folder

    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise ScanReadError(f"--watch {folder}: {'is not a folder' if folder.exists() else 'no such folder'}")
    if until_scans is not None and until_scans < 1:
        raise UsageError(f"--until-scans must be at least 1, got {until_scans}")
    if poll_s <= 0:
        raise UsageError(f"--poll must be greater than 0, got {poll_s}")
    out_dir = plot_folder(out, [folder])
    watch = Watch(
        folder.resolve(),
        out_dir,
        params,
        centre=centre,
        scanner_params=scanner_params,
        plan_params=plan_params,
        on_event=on_event,
        progress=progress,
        cancel=cancel,
    )
    resumed = watch.resume()
    if on_start is not None:
        on_start(resumed)
    stopped = False
    try:
        while until_scans is None or len(watch.taken()) < until_scans:
            watch.step()
            if until_scans is not None and len(watch.taken()) >= until_scans:
                break
            sleep(poll_s)
    except KeyboardInterrupt:
        stopped = True
    placed, taken = tuple(watch.placed()), tuple(watch.taken())
    aside = {n: f.get("reason", "") for n, f in watch.files.items() if f.get("status") in SET_ASIDE}
    failed = bool(aside)
    reason = "; ".join(f"{n}: {r}" for n, r in aside.items())
    return WatchRun(
        status="failed" if failed else "ok",
        reason=reason,
        out=out_dir,
        placed=placed,
        taken=taken,
        aside=aside,
        stopped=stopped,
        events=tuple(watch.events),
        resumed=resumed,
    )
