"""What a finished run left in its output folder, read back as typed records: ``result.json`` (a
pair registration, a co-registration, a re-survey), ``poses.json`` (a plot) and ``project.json``
(its scans' files and scanner positions, each link's last status).

These readers use the standard library alone: the plugin hosts (QGIS, CloudCompare) read a job's
folder with them in a Python that has no NumPy, and the batch runner and the job service read the
same folders with them. Matrices are 4x4 nested lists of floats; a result's verdict is the one its
writer recorded (the writer applied the last rigid check). :func:`finite_or_none`,
:func:`count_or_none` and :func:`mapping_or_empty` read one saved figure or section; every typed
record of :mod:`forestreg.app` reads its figures with them.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Union

PathLike = Union[str, Path]
Matrix = list  # 4x4 nested lists of floats


class SavedFileError(ValueError):
    """A saved file is missing, unreadable or not the JSON object its reader expects."""


def read_json_object(path: PathLike) -> dict:
    """The JSON object in ``path``; :class:`SavedFileError` when it is missing, unreadable or not
    an object."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise SavedFileError(f"{p.name} is missing in {p.parent}") from exc
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise SavedFileError(f"{p}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise SavedFileError(f"{p}: not a JSON object")
    return data


def _matrix(value: Any) -> Optional[Matrix]:
    """A finite 4x4 as nested lists of floats, or None."""
    try:
        rows = [[float(v) for v in row] for row in value]
    except (TypeError, ValueError):
        return None
    if len(rows) != 4 or any(len(r) != 4 for r in rows) or not all(math.isfinite(v) for r in rows for v in r):
        return None
    return rows


def finite_or_none(value: Any) -> Optional[float]:
    """A saved figure as a float: None when it is missing, null, text, a boolean or not finite."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def count_or_none(value: Any) -> Optional[int]:
    """A saved count as an int (None as :func:`finite_or_none`)."""
    v = finite_or_none(value)
    return None if v is None else int(v)


def mapping_or_empty(value: Any) -> Mapping:
    """A saved section (a JSON object), or an empty one when it is missing or not an object."""
    return value if isinstance(value, Mapping) else {}


@dataclass(frozen=True)
class SavedResult:
    """A ``result.json``: ``status`` ("ok" or "failed"), ``reason``, ``matrix`` (None unless ok),
    the two inputs' names (``reference`` / ``moving`` of a pair), the matched trunk shadows or
    keypoints, the fine fit's standard deviation (ICP, m) and, for a re-survey, the trees per
    status."""

    status: str
    reason: str = ""
    matrix: Optional[Matrix] = None
    reference: str = ""
    moving: str = ""
    matched: Optional[int] = None
    icp_std_m: Optional[float] = None
    trees: Mapping[str, int] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "SavedResult":
        matrix = _matrix(d.get("matrix"))
        status = "ok" if d.get("status") == "ok" and matrix is not None else "failed"
        reason = str(d.get("reason") or ("no matrix; withheld" if d.get("status") == "ok" and matrix is None else ""))
        trees = d.get("trees") if isinstance(d.get("trees"), Mapping) else {}
        icp = d.get("icp") if isinstance(d.get("icp"), Mapping) else {}
        return cls(
            status,
            reason,
            matrix if status == "ok" else None,
            str(d.get("reference") or ""),
            str(d.get("moving") or ""),
            count_or_none(d.get("matched")),
            finite_or_none(icp.get("std_m")),
            {str(k): int(v) for k, v in trees.items() if count_or_none(v) is not None},
        )

    @classmethod
    def read(cls, path: PathLike) -> "SavedResult":
        """Read a ``result.json`` (:class:`SavedFileError` when missing or unreadable)."""
        return cls.from_dict(read_json_object(path))

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def saved_crs(d: object) -> Optional[str]:
    """The CRS a run's outputs are in, as its ``result.json`` or ``poses.json`` names it (its
    ``crs`` entry): the EPSG id (``"EPSG:32618"``), else the WKT; None for local coordinates or
    no such entry. Text only, without pyproj (:meth:`~forestreg.engine.io.crs.Crs.from_dict`
    parses it): the QGIS plugin reads it in QGIS's own Python."""
    crs = d.get("crs") if isinstance(d, Mapping) else None
    if not isinstance(crs, Mapping):
        return None
    found = crs.get("epsg") or crs.get("wkt")
    return str(found) if found else None


@dataclass(frozen=True)
class SavedPose:
    """One scan of ``poses.json``: its status, reason, the scan it was placed on and ``matrix``
    (``p_centre = matrix @ p_scan``, file coordinates; None when not registered)."""

    name: str
    status: str
    reason: str = ""
    reference: str = ""
    matrix: Optional[Matrix] = None

    @property
    def registered(self) -> bool:
        return self.matrix is not None


@dataclass(frozen=True)
class SavedPoses:
    """A plot's ``poses.json``: the centre scan (``frame``) and every scan's pose, in file order."""

    frame: str
    scans: tuple[SavedPose, ...] = ()

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "SavedPoses":
        scans = d.get("scans") if isinstance(d.get("scans"), Mapping) else {}
        poses = []
        for name, e in scans.items():
            e = e if isinstance(e, Mapping) else {}
            poses.append(
                SavedPose(
                    str(name),
                    str(e.get("status") or "failed"),
                    str(e.get("reason") or ""),
                    str(e.get("reference") or ""),
                    _matrix(e.get("matrix")),
                )
            )
        return cls(str(d.get("frame") or ""), tuple(poses))

    @classmethod
    def read(cls, path: PathLike) -> "SavedPoses":
        """Read a ``poses.json`` (:class:`SavedFileError` when missing or unreadable)."""
        return cls.from_dict(read_json_object(path))

    @property
    def not_registered(self) -> list[SavedPose]:
        return [s for s in self.scans if not s.registered]

    def reason(self) -> str:
        """``scan: reason`` of every scan not registered, joined by "; " ("" when all are)."""
        return "; ".join(f"{s.name}: {s.reason or 'not registered'}" for s in self.not_registered)


@dataclass(frozen=True)
class SavedScan:
    """One scan of a ``project.json``: its name, its file (resolved against the project's folder)
    and the scanner position given for it (file coordinates; None when not given)."""

    name: str
    path: Path
    scanner_position: Optional[tuple[float, float, float]] = None


@dataclass(frozen=True)
class SavedProject:
    """A plot's ``project.json``: its scans and the status of each link's last run ("" when the
    link has not run)."""

    scans: tuple[SavedScan, ...] = ()
    link_statuses: tuple[str, ...] = ()

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], folder: PathLike = ".") -> "SavedProject":
        """The project of a ``project.json`` dict whose relative paths start at ``folder``;
        :class:`SavedFileError` when a scan has no file or a position is not three numbers."""
        scans = []
        for s in d.get("scans") or []:
            s = mapping_or_empty(s)
            if not isinstance(s.get("path"), str):
                raise SavedFileError(f"project: scan {s.get('name')!r} has no file")
            position = s.get("scanner_position")
            try:
                xyz = tuple(float(v) for v in position[:3]) if position else None
            except (TypeError, ValueError) as exc:
                raise SavedFileError(
                    f"project: scan {s.get('name')!r}: the scanner position is not three numbers"
                ) from exc
            scans.append(SavedScan(str(s.get("name") or ""), (Path(folder) / s.get("path")).resolve(), xyz))
        links = [mapping_or_empty(link) for link in d.get("links") or [] if isinstance(link, Mapping)]
        return cls(tuple(scans), tuple(str(mapping_or_empty(link.get("result")).get("status") or "") for link in links))

    @classmethod
    def read(cls, path: PathLike) -> "SavedProject":
        """Read a ``project.json`` (:class:`SavedFileError` when missing, unreadable or malformed)."""
        return cls.from_dict(read_json_object(path), Path(path).parent)

    @property
    def links_ok(self) -> int:
        """Links whose last run succeeded."""
        return sum(1 for status in self.link_statuses if status == "ok")


def read_scanner_positions(project_file: PathLike) -> dict[str, tuple[float, float, float]]:
    """Scan name -> the scanner position given in a ``project.json`` (file coordinates; scans
    without one are left out)."""
    return {s.name: s.scanner_position for s in SavedProject.read(project_file).scans if s.scanner_position is not None}
