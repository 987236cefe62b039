"""The plot project: scans, the centre scan, links (moving -> reference), targets and results.

A project is what a user registers in one go: the scans of one plot, each linked to the scan it is
registered onto. It is saved as a versioned JSON file with scan paths relative to it, written
atomically; a damaged or newer file gives a :class:`~forestreg.engine.core.errors.ProjectFileError` and
is never overwritten by a failed read.

Frames: the project frame is the centre (root) scan's file coordinates. A scan's pose maps its own
file coordinates into the project frame; a link's matrix maps the moving scan's file coordinates
into the reference scan's (``p_reference = matrix @ p_moving``), so poses compose along links.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..core.errors import InvalidArgumentError, ProjectFileError, UnknownNameError
from ..core.names import safe_name
from ..core.outcome import OutcomeRecord
from ..io.results import ProjectFile
from .params import RegistrationParams, ScannerPositionParams

FORMAT = "forestreg-project"
VERSION = 1


@dataclass
class ScanEntry:
    """One scan of the project.

    ``path`` is absolute in memory and relative to the project file on disk. ``scanner_position``
    (file coordinates) is None for a scan in its scanner's own coordinates. ``targets`` maps target
    ids to centres in the scan's file coordinates. ``level_partner`` names the level scan a tilted
    scan was taken beside.
    """

    name: str
    path: Path
    scanner_position: Optional[tuple[float, float, float]] = None
    scan_index: Optional[int] = None
    tilted: bool = False
    level_partner: Optional[str] = None
    prior_pose: Optional[np.ndarray] = None
    targets: dict[str, np.ndarray] = field(default_factory=dict)


class LinkResult(OutcomeRecord):
    """The outcome of a link's last run, typed (status, reason, matrix, evidence, timings) over
    its JSON form (the result's ``to_dict()``, also readable as a mapping: ``r["matched"]``)."""

    @property
    def matched(self) -> Optional[int]:
        """Matched trunk shadows (auto links), None otherwise."""
        m = self.data.get("matched")
        return None if m is None else int(m)

    @property
    def uncertainty(self) -> dict[str, Any]:
        """The calibrated standard errors and their covariance (empty when not computed)."""
        u = self.data.get("uncertainty")
        return dict(u) if isinstance(u, dict) else {}


@dataclass
class Link:
    """A registration of ``moving`` onto ``reference`` and its outcome.

    ``method`` is "auto" (trunk shadows) or "manual" (targets). ``vop_radius_m`` and
    ``slice_offsets_m`` override the project parameters for this link. ``result`` is the
    :class:`LinkResult` of the last run (None until run; a result dict assigned to it is read into
    one); ``matrix`` its 4x4 when it succeeded. An ``extra`` link does not place its scan; it
    closes a loop for the global adjustment.
    """

    moving: str
    reference: str
    method: str = "auto"
    vop_radius_m: Optional[float] = None
    slice_offsets_m: Optional[tuple[float, ...]] = None
    result: Optional[LinkResult] = None
    extra: bool = False

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "result" and value is not None and type(value) is not LinkResult:
            value = LinkResult.from_dict(value)
        object.__setattr__(self, name, value)

    @property
    def ok(self) -> bool:
        return self.result is not None and self.result.ok

    @property
    def matrix(self) -> Optional[np.ndarray]:
        if not self.ok or self.result.matrix is None:
            return None
        return np.array(self.result.matrix, dtype=float)

    def params(self, base: RegistrationParams) -> RegistrationParams:
        """The project parameters with this link's overrides."""
        changes: dict[str, Any] = {}
        if self.vop_radius_m is not None:
            changes["vop_radius_m"] = self.vop_radius_m
        if self.slice_offsets_m is not None:
            changes["slice_offsets_m"] = tuple(self.slice_offsets_m)
        return base.replace(**changes) if changes else base


@dataclass
class Project(ProjectFile):
    """Scans, links and results of one plot (see the module docstring for frames)."""

    name: str = "plot"
    centre: Optional[str] = None
    scans: list[ScanEntry] = field(default_factory=list)
    links: list[Link] = field(default_factory=list)
    params: RegistrationParams = field(default_factory=RegistrationParams)
    #: how a scan whose file does not say where its scanner stood is located
    scanner_params: ScannerPositionParams = field(default_factory=ScannerPositionParams)
    path: Optional[Path] = None
    adjustment: Optional[dict[str, Any]] = None
    #: System B: clouds and results beyond the TLS scans (see :class:`ForestResults`)
    forest: "ForestResults" = field(default_factory=lambda: ForestResults())

    # ------------------------------------------------------------------ editing

    def add_scan(self, path: str | Path, *, name: Optional[str] = None, **options: Any) -> ScanEntry:
        """Add a scan file; its name defaults to the file name (made unique)."""
        p = Path(path).resolve()
        base = safe_name(name, "a scan's name") if name else p.name
        unique, k = base, 2
        while self.has_scan(unique):
            unique, k = f"{base}#{k}", k + 1
        entry = ScanEntry(name=unique, path=p, **options)
        self.scans.append(entry)
        if self.centre is None:
            self.centre = unique
        return entry

    def has_scan(self, name: str) -> bool:
        return any(s.name == name for s in self.scans)

    def scan(self, name: str) -> ScanEntry:
        for s in self.scans:
            if s.name == name:
                return s
        raise UnknownNameError(
            f"no scan named {name!r} in the project (scans: {', '.join(s.name for s in self.scans)})"
        )

    def link_of(self, moving: str) -> Optional[Link]:
        """The link that places ``moving`` (its non-extra link)."""
        return next((link for link in self.links if link.moving == moving and not link.extra), None)

    def remove_scan(self, name: str) -> None:
        """Remove a scan and every link naming it (the first scan left becomes centre if it was)."""
        self.scan(name)
        self.scans = [s for s in self.scans if s.name != name]
        self.links = [link for link in self.links if name not in (link.moving, link.reference)]
        for s in self.scans:
            if s.level_partner == name:
                s.level_partner = None
        if self.centre == name:
            self.centre = self.scans[0].name if self.scans else None

    def set_centre(self, name: str) -> None:
        """Make a scan the centre, the project frame: the link that placed it goes (its extra
        links and the other scans' links stay)."""
        self.scan(name)
        self.centre = name
        self.links = [link for link in self.links if link.moving != name or link.extra]

    def _check_link(self, moving: str, reference: str) -> None:
        """The rules of every link: both scans exist, and a scan is not linked to itself."""
        self.scan(moving), self.scan(reference)
        if moving == reference:
            raise InvalidArgumentError(f"a scan cannot be linked to itself ({moving})")

    def set_link(self, moving: str, reference: str, **options: Any) -> Link:
        """Link ``moving`` to ``reference``, replacing the link that placed it. The centre scan
        defines the project frame and is not moved: it has no placing link (an extra link from it,
        :meth:`add_link`, closes a loop)."""
        self._check_link(moving, reference)
        if moving == self.centre:
            raise InvalidArgumentError(
                f"{moving} is the centre scan: it defines the project frame and is not moved. "
                "Mark another scan as centre first."
            )
        self.links = [link for link in self.links if link.moving != moving or link.extra]
        link = Link(moving=moving, reference=reference, **options)
        self.links.append(link)
        return link

    def add_link(self, moving: str, reference: str, **options: Any) -> Link:
        """Add an extra link (beside the link that places the scan): a loop for the global
        adjustment."""
        self._check_link(moving, reference)
        link = Link(moving=moving, reference=reference, extra=True, **options)
        self.links.append(link)
        return link

    def replace_link(self, old: Link, new: Link) -> None:
        """Put ``new`` where ``old`` stands in the link list (keeps which link is first)."""
        self.links = [new if link is old else link for link in self.links]

    # ------------------------------------------------------------------ poses

    def poses(self) -> dict[str, Optional[np.ndarray]]:
        """Each scan's pose in the project frame (None where its chain of links to the centre is
        broken or failed), composed along the links."""
        if self.adjustment and self.adjustment.get("poses"):
            return {k: (None if v is None else np.array(v)) for k, v in self.adjustment["poses"].items()}
        return self.chained_poses()

    def chained_poses(self) -> dict[str, Optional[np.ndarray]]:
        """Poses composed along the (first) link of each scan, ignoring any adjustment."""
        poses: dict[str, Optional[np.ndarray]] = {s.name: None for s in self.scans}
        if self.centre is None:
            return poses
        poses[self.centre] = np.eye(4)

        def resolve(name: str, seen: tuple[str, ...]) -> Optional[np.ndarray]:
            if poses.get(name) is not None:
                return poses[name]
            link = self.link_of(name)
            if link is None or name in seen or link.matrix is None:
                return None
            parent = resolve(link.reference, seen + (name,))
            if parent is None:
                return None
            poses[name] = parent @ link.matrix
            return poses[name]

        for s in self.scans:
            resolve(s.name, ())
        return poses

    # ------------------------------------------------------------------ files

    def to_dict(self, relative_to: Optional[Path] = None) -> dict[str, Any]:
        def rel(p: Path) -> str:
            if relative_to is None:
                return str(p)
            try:
                return str(Path(p).resolve().relative_to(relative_to.resolve()))
            except ValueError:
                return os.path.relpath(Path(p).resolve(), relative_to.resolve())

        return {
            "format": FORMAT,
            "version": VERSION,
            "name": self.name,
            "centre": self.centre,
            "parameters": self.params.to_dict(),
            "scanner_position_parameters": self.scanner_params.to_dict(),
            "scans": [
                {
                    "name": s.name,
                    "path": rel(s.path),
                    "scanner_position": None if s.scanner_position is None else list(s.scanner_position),
                    "scan_index": s.scan_index,
                    "tilted": s.tilted,
                    "level_partner": s.level_partner,
                    "prior_pose": None if s.prior_pose is None else np.asarray(s.prior_pose).tolist(),
                    "targets": {k: np.asarray(v).tolist() for k, v in s.targets.items()},
                }
                for s in self.scans
            ],
            "links": [
                {
                    "moving": link.moving,
                    "reference": link.reference,
                    "method": link.method,
                    "vop_radius_m": link.vop_radius_m,
                    "slice_offsets_m": None if link.slice_offsets_m is None else list(link.slice_offsets_m),
                    "result": None if link.result is None else link.result.to_dict(),
                    "extra": link.extra,
                }
                for link in self.links
            ],
            "adjustment": self.adjustment,
            **({"forest": self.forest.to_dict(rel)} if not self.forest.empty else {}),
        }

    @classmethod
    def load(cls, path: str | Path) -> "Project":
        """Read a project file; scan paths are resolved relative to it."""
        p = Path(path)
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError as exc:
            raise ProjectFileError(f"project file {p} does not exist") from exc
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ProjectFileError(
                f"project file {p} is damaged and cannot be read ({exc}); it was left untouched"
            ) from exc
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ProjectFileError(f"{p} is not a forestreg project file")
        version = data.get("version")
        if not isinstance(version, int) or isinstance(version, bool):
            raise ProjectFileError(
                f"project file {p} is damaged: its format version is {version!r}, not a whole number; it was left untouched"
            )
        if version > VERSION:
            raise ProjectFileError(
                f"{p} was written by a newer forestreg (project format {version}; this one reads up to {VERSION})"
            )
        if version < 1:
            raise ProjectFileError(f"{p} has an unsupported old project format {version}")
        try:
            folder = p.resolve().parent
            scans = [
                ScanEntry(
                    name=_scan_name(p, s["name"]),
                    path=(folder / s["path"]).resolve(),
                    scanner_position=None
                    if s.get("scanner_position") is None
                    else tuple(float(v) for v in s["scanner_position"]),
                    scan_index=s.get("scan_index"),
                    tilted=bool(s.get("tilted", False)),
                    level_partner=s.get("level_partner"),
                    prior_pose=None if s.get("prior_pose") is None else np.array(s["prior_pose"], dtype=float),
                    targets={str(k): np.array(v, dtype=float) for k, v in (s.get("targets") or {}).items()},
                )
                for s in data["scans"]
            ]
            raw_links = data.get("links", [])
            _check_matrices(p, scans, raw_links)
            links = [
                Link(
                    moving=str(link["moving"]),
                    reference=str(link["reference"]),
                    method=str(link.get("method", "auto")),
                    vop_radius_m=link.get("vop_radius_m"),
                    slice_offsets_m=None if link.get("slice_offsets_m") is None else tuple(link["slice_offsets_m"]),
                    result=link.get("result"),
                    extra=bool(link.get("extra", False)),
                )
                for link in raw_links
            ]
            params = RegistrationParams.from_mapping(data.get("parameters") or {})
            scanner_params = ScannerPositionParams.from_mapping(data.get("scanner_position_parameters") or {})
            forest = ForestResults.from_dict(data.get("forest") or {}, folder)
        except (KeyError, TypeError, ValueError) as exc:
            raise ProjectFileError(f"project file {p} is damaged ({exc!r}); it was left untouched") from exc
        project = cls(
            name=str(data.get("name", p.stem)),
            centre=data.get("centre"),
            scans=scans,
            links=links,
            params=params,
            scanner_params=scanner_params,
            path=p.resolve(),
            adjustment=data.get("adjustment"),
            forest=forest,
        )
        names = {s.name for s in scans}
        bad = [link for link in links if link.moving not in names or link.reference not in names]
        if bad or (project.centre is not None and project.centre not in names):
            raise ProjectFileError(f"project file {p} refers to scans it does not list; it was left untouched")
        return project


def _check_matrices(path: Path, scans: list[ScanEntry], links: list[dict[str, Any]]) -> None:
    """Every 4x4 of a project file (link results as read, prior poses) is a finite proper rigid
    transform (no scale, no reflection); otherwise :class:`ProjectFileError` naming it."""
    from ..core.errors import TransformError
    from ..core.transform import check_rigid

    try:
        for s in scans:
            if s.prior_pose is not None:
                check_rigid(s.prior_pose, f"the prior pose of {s.name}")
        for link in links:
            if not isinstance(link, dict):
                raise ProjectFileError(
                    f"project file {path} is damaged (a link is {type(link).__name__}, not an object); it was left untouched"
                )
            r, moving, reference = link.get("result"), link["moving"], link["reference"]
            if isinstance(r, dict) and r.get("matrix") is not None:
                check_rigid(r["matrix"], f"the link {moving} -> {reference}")
            if moving == reference:
                raise ProjectFileError(
                    f"project file {path}: the scan {moving} is linked to itself; it was left untouched"
                )
    except TransformError as exc:
        raise ProjectFileError(f"project file {path}: {exc}; it was left untouched") from exc


@dataclass
class ForestResults:
    """The System B part of a project: the ground-based cloud (the registered plot or a
    backpack/handheld file), UAV/ALS clouds, the co-registration result folder and the user's
    decision on it ("", "accepted", "rejected"), the fused cloud, tree result folders by name
    (e.g. "ground", "fused"), the field data file, and the tree edits made by hand
    (:meth:`forestreg.engine.trees.edit.TreeEdit.to_dict` records, in order). Paths are absolute
    in memory and relative to the project file on disk."""

    ground_cloud: Optional[Path] = None
    uav_clouds: list[Path] = field(default_factory=list)
    coregistration: Optional[Path] = None
    coregistration_decision: str = ""
    fused_cloud: Optional[Path] = None
    trees: dict[str, Path] = field(default_factory=dict)
    field_data: Optional[Path] = None
    tree_edits: list[dict[str, Any]] = field(default_factory=list)

    @property
    def empty(self) -> bool:
        return not (
            self.ground_cloud
            or self.uav_clouds
            or self.coregistration
            or self.fused_cloud
            or self.trees
            or self.field_data
            or self.tree_edits
            or self.coregistration_decision
        )

    def to_dict(self, rel: Any = str) -> dict[str, Any]:
        """JSON form; ``rel`` turns an absolute path into the stored (relative) text."""

        def one(p: Optional[Path]) -> Optional[str]:
            return None if p is None else rel(Path(p))

        return {
            "ground_cloud": one(self.ground_cloud),
            "uav_clouds": [rel(Path(p)) for p in self.uav_clouds],
            "coregistration": one(self.coregistration),
            "coregistration_decision": self.coregistration_decision,
            "fused_cloud": one(self.fused_cloud),
            "trees": {k: rel(Path(v)) for k, v in self.trees.items()},
            "field_data": one(self.field_data),
            "tree_edits": list(self.tree_edits),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], folder: Path) -> "ForestResults":
        """Read :meth:`to_dict`'s form, paths resolved against the project's folder."""

        def one(v: Any) -> Optional[Path]:
            return None if v in (None, "") else (Path(folder) / str(v)).resolve()

        decision = str(d.get("coregistration_decision") or "")
        if decision not in ("", "accepted", "rejected"):
            raise ValueError(f"unknown co-registration decision {decision!r}")
        return cls(
            ground_cloud=one(d.get("ground_cloud")),
            uav_clouds=[one(v) for v in d.get("uav_clouds") or [] if v],
            coregistration=one(d.get("coregistration")),
            coregistration_decision=decision,
            fused_cloud=one(d.get("fused_cloud")),
            trees={str(k): one(v) for k, v in (d.get("trees") or {}).items() if v},
            field_data=one(d.get("field_data")),
            tree_edits=[dict(e) for e in d.get("tree_edits") or []],
        )


def _scan_name(project_file: Path, name: Any) -> str:
    """A scan's name read from a project file, refused (the file named) when it could not be a
    file name: registered scans and pose files are written under it."""
    try:
        return safe_name(name, "scan name")
    except InvalidArgumentError as exc:
        raise ProjectFileError(f"{project_file}: {exc}") from exc
