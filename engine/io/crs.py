"""Coordinate reference systems (CRS): read from point files, given by the user, carried to outputs.

A cloud's CRS says what its *file coordinates* mean on the Earth (e.g. UTM zone 18N, metres). It
is read from a LAS/LAZ file's WKT or GeoTIFF-key VLRs (laspy's ``header.parse_crs``, which needs
pyproj) and from an E57 file's ``coordinateMetadata`` when that names one; a file without one is in
*local* coordinates, and the command line's ``--crs`` (e.g. ``EPSG:32618``) names the CRS of such
a file, or of the outputs where two inputs disagree (:func:`forestreg.engine.io.read_crs` reads a
file's without its points). A scan keeps the CRS of its file in
``scan.meta["crs"]`` (:class:`Crs`); moving a scan (:meth:`~forestreg.engine.core.scan.Scan.transformed`)
drops it, since the moved points are in another frame.

Outputs carry the CRS of the frame they are in (:class:`FrameCrs`): a pair registered onto the
reference scan takes the reference's, a plot the centre scan's, a co-registration and a fusion the
UAV cloud's, a re-survey BEFORE's. LAS/LAZ/COPC outputs get a WKT VLR, ``result.json`` a ``crs``
entry, ``layers.gpkg`` the CRS of its layers. Without pyproj nothing is read (every file is local)
and nothing is written.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional

log = logging.getLogger("forestreg.io")

__all__ = ["Crs", "FrameCrs", "as_crs", "crs_of", "crs_of_e57_root", "crs_of_las_header", "frame_crs", "parse_crs"]

#: The LAS VLRs that hold a CRS (laspy's class names).
_CRS_VLRS = ("WktCoordinateSystemVlr", "GeoKeyDirectoryVlr")


def _pyproj():
    """pyproj, or None when it is not installed (every file is then read as local)."""
    try:
        import pyproj
    except ImportError:  # pragma: no cover - a dependency; kept optional for embedded hosts
        return None
    return pyproj


@dataclass(frozen=True)
class Crs:
    """A coordinate reference system: ``wkt`` (OGC WKT2 as pyproj writes it), ``epsg`` (``"EPSG:n"``,
    or ``"EPSG:h+v"`` for a compound CRS of a horizontal and a vertical EPSG code; None when it has
    no code) and ``name`` (e.g. "WGS 84 / UTM zone 18N")."""

    wkt: str
    epsg: Optional[str]
    name: str
    #: the WKT1 (GDAL flavour) of the CRS, for formats that read that one (GeoPackage), "" when none
    wkt1: str = field(default="", compare=False)

    @classmethod
    def from_pyproj(cls, crs) -> "Crs":
        """The :class:`Crs` of a ``pyproj.CRS``."""
        code = _epsg_of(crs)
        try:
            wkt1 = crs.to_wkt("WKT1_GDAL") or ""
        except Exception:  # noqa: BLE001 - a CRS WKT1 cannot express
            wkt1 = ""
        return cls(wkt=crs.to_wkt(), epsg=code, name=str(crs.name), wkt1=wkt1)

    @property
    def label(self) -> str:
        """``EPSG:32618 (WGS 84 / UTM zone 18N)``, or the name alone without a code."""
        return f"{self.epsg} ({self.name})" if self.epsg else self.name

    @property
    def epsg_code(self) -> Optional[int]:
        """The single EPSG code (None for none, or a compound of two)."""
        if not self.epsg or "+" in self.epsg:
            return None
        return int(self.epsg.split(":", 1)[1])

    def to_pyproj(self):
        """The ``pyproj.CRS`` (None without pyproj)."""
        pyproj = _pyproj()
        return None if pyproj is None else _from_wkt(pyproj, self.wkt)

    def same_as(self, other: Optional["Crs"]) -> bool:
        """Whether ``other`` is the same CRS: the same EPSG code(s) when both have them, else
        pyproj's comparison (axis order aside), else the same WKT."""
        if other is None:
            return False
        if self.epsg and other.epsg:
            return self.epsg == other.epsg
        a, b = self.to_pyproj(), other.to_pyproj()
        if a is not None and b is not None:
            return bool(a.equals(b, ignore_axis_order=True))
        return self.wkt == other.wkt

    def to_dict(self) -> dict[str, Any]:
        """``{"epsg": "EPSG:n" or None, "name", "wkt"}`` (for ``result.json``)."""
        return {"epsg": self.epsg, "name": self.name, "wkt": self.wkt}

    @classmethod
    def from_dict(cls, d: Any) -> Optional["Crs"]:
        """The CRS of a ``result.json`` ``crs`` entry (None when it names none)."""
        if not isinstance(d, Mapping):
            return None
        wkt, code = d.get("wkt"), d.get("epsg")
        if wkt:
            return _cached_parse(str(wkt))
        if code:
            return _cached_parse(str(code))
        return None


@functools.lru_cache(maxsize=64)
def _from_wkt(pyproj, wkt: str):
    return pyproj.CRS.from_wkt(wkt)


def _epsg_of(crs) -> Optional[str]:
    """``"EPSG:n"`` of a pyproj CRS, ``"EPSG:h+v"`` for a compound one whose parts have codes."""
    try:
        code = crs.to_epsg()
        if code is not None:
            return f"EPSG:{code}"
        if crs.is_compound:
            parts = [c.to_epsg() for c in crs.sub_crs_list]
            if parts and all(p is not None for p in parts):
                return "EPSG:" + "+".join(str(p) for p in parts)
    except Exception:  # noqa: BLE001 - a CRS pyproj cannot look up: no code
        pass
    return None


@functools.lru_cache(maxsize=64)
def _cached_parse(text: str) -> Optional[Crs]:
    pyproj = _pyproj()
    if pyproj is None:
        return None
    try:
        return Crs.from_pyproj(pyproj.CRS.from_user_input(text))
    except Exception:  # noqa: BLE001 - pyproj's CRSError and friends
        return None


def parse_crs(text: str, what: str = "--crs") -> Crs:
    """The CRS a user named: ``EPSG:32618``, ``32618``, ``EPSG:6341+5703`` (compound), a WKT or a
    PROJ string; :class:`~forestreg.engine.core.errors.UsageError` (exit 2) when it names none."""
    from ..core.errors import UsageError

    value = str(text).strip()
    if value.isdigit():
        value = f"EPSG:{value}"
    if _pyproj() is None:
        raise UsageError(f"{what} {text}: reading a CRS needs pyproj (pip install pyproj)")
    found = _cached_parse(value) if value else None
    if found is None:
        raise UsageError(
            f"{what} {text!r} is not a coordinate reference system: give one as EPSG:CODE (e.g. EPSG:32618), a WKT or a PROJ string"
        )
    return found


def as_crs(value: Any, what: str = "crs") -> Optional[Crs]:
    """``value`` as a :class:`Crs`: None, a :class:`Crs`, a text :func:`parse_crs` reads, a whole
    number (an EPSG code) or a ``result.json`` ``crs`` entry."""
    if value is None or isinstance(value, Crs):
        return value
    if isinstance(value, Mapping):
        return Crs.from_dict(value)
    if isinstance(value, int) and not isinstance(value, bool):
        return parse_crs(str(value), what)
    if isinstance(value, str):
        return parse_crs(value, what)
    if hasattr(value, "to_wkt"):  # a pyproj.CRS
        return Crs.from_pyproj(value)
    from ..core.errors import InvalidArgumentError

    raise InvalidArgumentError(f"{what}: expected a CRS (e.g. 'EPSG:32618'), got {type(value).__name__}")


def crs_of_las_header(header) -> Optional[Crs]:
    """The CRS a laspy header's VLRs (WKT or GeoTIFF keys) hold, None when they hold none, pyproj
    is missing or the VLRs cannot be understood (logged)."""
    vlrs = list(getattr(header, "vlrs", []) or []) + list(getattr(header, "evlrs", None) or [])
    if not any(type(v).__name__ in _CRS_VLRS for v in vlrs):
        return None
    if _pyproj() is None:
        log.info("the file declares a CRS; pyproj is not installed, so it is not read")
        return None
    try:
        found = header.parse_crs()
    except Exception as exc:  # noqa: BLE001 - damaged or unusual CRS records: the file stays usable
        log.warning("the CRS records of a LAS/LAZ file cannot be read (%s): its coordinates are taken as local", exc)
        return None
    return None if found is None else Crs.from_pyproj(found)


def crs_of_e57_root(root) -> Optional[Crs]:
    """The CRS an E57 file's ``coordinateMetadata`` names (a WKT, ``EPSG:n``), None when empty or
    not a CRS."""
    try:
        if not root.isDefined("coordinateMetadata"):
            return None
        text = str(root["coordinateMetadata"].value()).strip()
    except Exception:  # noqa: BLE001 - libE57 errors: no CRS
        return None
    return _cached_parse(text) if text else None


def crs_of(scan) -> Optional[Crs]:
    """The CRS of a :class:`~forestreg.engine.core.scan.Scan` (its file's, None when local or moved)."""
    meta = getattr(scan, "meta", None) or {}
    found = meta.get("crs")
    return found if isinstance(found, Crs) else None


@dataclass(frozen=True)
class FrameCrs:
    """The CRS of a run's outputs and of each input.

    ``crs`` is the CRS of the frame the outputs are in (None: local coordinates), ``source`` where
    it came from ("file NAME", "--crs", or "" when none), ``frame`` the input whose frame the
    outputs are in (e.g. "uav"), ``inputs`` each input's CRS as its file declares it (role ->
    CRS or None), ``names`` each input's file name, ``notes`` what a user should know (inputs
    that disagree, a file's CRS that ``--crs`` overrode)."""

    crs: Optional[Crs]
    source: str
    frame: str
    inputs: Mapping[str, Optional[Crs]] = field(default_factory=dict)
    names: Mapping[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    @property
    def agree(self) -> bool:
        """Whether every input declares the same CRS (or none does)."""
        found = list(self.inputs.values())
        if all(c is None for c in found):
            return True
        return all(c is not None and c.same_as(found[0]) for c in found)

    def label_of(self, role: str) -> str:
        """One input's frame in words: ``uav.laz: EPSG:32618 (WGS 84 / UTM zone 18N)``."""
        c = self.inputs.get(role)
        return f"{self.names.get(role, role)}: {c.label if c is not None else 'no CRS (local coordinates)'}"

    def to_dict(self, frames: Optional[Mapping[str, str]] = None) -> dict[str, Any]:
        """The ``result.json`` ``crs`` entry: ``epsg``, ``name``, ``wkt`` (None and "none (local
        coordinates)" without a CRS), ``source``, ``frame``, ``inputs`` (role -> the CRS its file
        declares, in words) and, when the inputs disagree or ``--crs`` overrode a file's, ``frames``
        (output -> the frame it is in, ``frames`` given by the caller) and ``notes``."""
        d: dict[str, Any] = (
            self.crs.to_dict()
            if self.crs is not None
            else {"epsg": None, "name": "none (local coordinates)", "wkt": None}
        )
        d["source"] = self.source
        d["frame"] = self.frame
        d["inputs"] = {role: (c.label if c is not None else None) for role, c in self.inputs.items()}
        if frames and (not self.agree or self.notes):
            d["frames"] = dict(frames)
        if self.notes:
            d["notes"] = list(self.notes)
        return d


def frame_crs(
    inputs: Mapping[str, Optional[Crs]],
    frame: str,
    given: Optional[Crs] = None,
    *,
    names: Optional[Mapping[str, str]] = None,
    refuse_mixed: str = "",
) -> FrameCrs:
    """The CRS of outputs in the frame of the input ``frame`` (a role of ``inputs``: role -> the
    CRS its file declares): ``given`` (``--crs``) when there is one, else that input's own.

    ``refuse_mixed`` (what the run does, e.g. "fuse"): inputs whose files declare two different
    CRSs are refused (:class:`~forestreg.engine.core.errors.UsageError`, exit 2) unless ``given``
    says which one wins."""
    from ..core.errors import UsageError

    names = dict(names or {})
    name = {role: names.get(role, role) for role in inputs}
    declared = {role: c for role, c in inputs.items() if c is not None}
    notes = []
    roles = list(declared)
    differ = [(a, b) for i, a in enumerate(roles) for b in roles[i + 1 :] if not declared[a].same_as(declared[b])]
    if differ and refuse_mixed and given is None:
        a, b = differ[0]
        raise UsageError(
            f"cannot {refuse_mixed} clouds in two CRSs: {name[a]} is in {declared[a].label}, {name[b]} in "
            f"{declared[b].label}; give --crs with the one the output is in"
        )
    if given is not None:
        crs, source = given, "--crs"
        for role, c in declared.items():
            if not c.same_as(given):
                notes.append(f"{name[role]} declares {c.label}; --crs {given.epsg or given.name} wins")
    else:
        crs = inputs.get(frame)
        source = f"file {name.get(frame, frame)}" if crs is not None else ""
    if crs is not None and given is None:
        for role, c in inputs.items():
            if c is None and role != frame:
                notes.append(f"{name[role]} declares no CRS (local coordinates)")
    elif declared:
        notes.append(
            f"the outputs are in {name.get(frame, frame)}'s frame, which declares no CRS (give --crs); "
            + ", ".join(f"{name[r]} is in {c.label}" for r, c in declared.items())
        )
    for a, b in differ:
        if given is None:
            notes.append(f"{name[a]} is in {declared[a].label}, {name[b]} in {declared[b].label}")
    return FrameCrs(crs=crs, source=source, frame=frame, inputs=dict(inputs), names=name, notes=tuple(notes))
