"""Reading and writing scan files: LAS/LAZ, PLY, PCD, E57 and ASCII point lists.

Reading picks the format from the file's first bytes (``LASF``, ``ply``, ``# .PCD``/``VERSION``,
``ASTM-E57``) and falls back to the suffix only for text, so a LAZ saved as ``.txt`` still reads.
Every problem with the file itself raises :class:`~forestreg.engine.core.errors.ScanReadError` with
one sentence naming the file (the library's exception is kept as ``__cause__``); problems with the
points (NaN, wrong units, too few) raise :class:`~forestreg.engine.core.errors.ScanDataError` from
:meth:`Scan.from_points <forestreg.engine.core.scan.Scan.from_points>`.

Writing picks the format from the suffix and always goes through a temporary file renamed onto
the target, so a failed write leaves no partial file and the previous file intact. A name ending in
``.copc.laz`` is written as COPC (:mod:`~forestreg.engine.io.copc`: a LAZ whose points are laid out
in octree nodes, which viewers stream), out of core like chunked LAS/LAZ.

Frames: readers return file coordinates (scaled to metres by ``unit_scale``); an E57 scan's file
coordinates are its own coordinates and ``Scan.pose`` maps them into the E57 common frame. The
coordinate reference system a LAS/LAZ or E57 file declares is kept as ``scan.meta["crs"]``
(:mod:`~forestreg.engine.io.crs`); LAS/LAZ/COPC writers store the CRS they are given as a WKT VLR.
"""

from __future__ import annotations

import operator
import os
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np

from ..core.atomic import atomic_path
from ..core.errors import ForestregError, ParameterError, ScanReadError, ScanWriteError
from ..core.scan import Scan
from . import copc as _copc
from . import e57 as _e57
from . import las as _las
from . import pcd as _pcd
from . import ply as _ply
from . import xyz as _xyz
from .base import (
    PathLike,
    PointsToWrite,
    RawCloud,
    as_column,
    as_matrix,
    as_points,
    build_scan,
    check_readable,
    check_unit_scale,
)
from .las import write_fused  # noqa: F401 - the fused cloud (System B)
from .sniff import READ_SUFFIXES, detect_format

__all__ = [
    "SUPPORTED_READ_SUFFIXES",
    "SUPPORTED_WRITE_SUFFIXES",
    "read_crs",
    "read_scan",
    "read_scans",
    "write_e57",
    "write_point_chunks",
    "write_points",
    "write_scan",
]

#: Suffixes (lower case) the readers accept; the content decides the format where it can.
SUPPORTED_READ_SUFFIXES: tuple[str, ...] = tuple(s for group in READ_SUFFIXES.values() for s in group)
#: Suffixes (lower case) :func:`write_scan` and :func:`write_points` can write (``.copc.laz``
#: names a COPC file, :mod:`~forestreg.engine.io.copc`).
SUPPORTED_WRITE_SUFFIXES: tuple[str, ...] = (".laz", ".las", ".ply", ".xyz", ".txt", ".e57")


# --------------------------------------------------------------------------------------- reading


def read_scan(
    path: PathLike,
    *,
    scanner_position: Optional[Sequence[float] | np.ndarray] = None,
    unit_scale: float = 1.0,
    scan_index: Optional[int] = None,
    with_intensity: bool = True,
) -> Scan:
    """Read one scan from a file.

    Parameters
    ----------
    path : a LAS/LAZ, PLY, PCD, E57 or ASCII (xyz/txt/csv/pts/asc) file.
    scanner_position : (3,) scanner position in file coordinates and file units; overrides the
        default (the file origin; for E57 the origin of the scan's own coordinates).
    unit_scale : metres per file unit (0.001 for mm, 0.01 for cm, 0.3048 for feet); multiplies
        the coordinates, the scanner position and an E57 pose translation.
    scan_index : which scan of a multi-scan E57 (0-based); not needed when the file has one.
    with_intensity : False: no intensity is read (LAS/LAZ: less memory, and a LAZ 1.4 file's
        layers other than x, y, z are not decompressed); work that uses the coordinates alone.

    Returns
    -------
    Scan
        Points in metres, ``meta["format"]`` and ``meta["unit_scale"]`` set; for E57 ``name``
        and ``pose`` come from the file.

    Raises
    ------
    ScanReadError
        Missing, empty, unreadable, truncated or corrupt file; unknown format; an E57 with several
        scans and no ``scan_index``, or an index out of range.
    ScanDataError
        The points are unusable (NaN, too few, an extent that says the unit is wrong).
    ParameterError
        ``unit_scale`` or ``scan_index`` is not a valid value.
    """
    scale = check_unit_scale(unit_scale)
    index = _check_index(scan_index)
    p = check_readable(path)
    fmt = detect_format(p)
    if fmt == "e57":
        count = _e57.scan_count(p)
        chosen = _pick_e57_index(p, count, index)
        raw = _e57.read_e57(p, [chosen])[0]
        return build_scan(
            raw,
            p,
            fmt="e57",
            unit_scale=scale,
            scanner_position=_position(scanner_position),
            label=f"scan {chosen} ({raw.name})" if count > 1 else None,
        )
    if index not in (None, 0):
        raise ScanReadError(f"{p}: holds a single scan; scan_index {index} does not exist (use 0 or leave it out)")
    raw, name = _read_single(p, fmt, with_intensity=with_intensity)
    return build_scan(raw, p, fmt=name, unit_scale=scale, scanner_position=_position(scanner_position))


def read_scans(path: PathLike, *, unit_scale: float = 1.0) -> list[Scan]:
    """Read every scan in a file: all scans of an E57 (in file order, each with its pose and
    name), or the one scan of any other format. See :func:`read_scan` for units and errors."""
    scale = check_unit_scale(unit_scale)
    p = check_readable(path)
    fmt = detect_format(p)
    if fmt != "e57":
        raw, name = _read_single(p, fmt)
        return [build_scan(raw, p, fmt=name, unit_scale=scale)]
    raws = _e57.read_e57(p)
    many = len(raws) > 1
    return [
        build_scan(raw, p, fmt="e57", unit_scale=scale, label=f"scan {i} ({raw.name})" if many else None)
        for i, raw in enumerate(raws)
    ]


def read_crs(path: PathLike):
    """The coordinate reference system a point file declares (:class:`~forestreg.engine.io.crs.Crs`),
    read from its header only: a LAS/LAZ file's WKT or GeoTIFF-key VLRs, an E57 file's
    ``coordinateMetadata``; None for other formats, files without one, or unreadable files."""
    suffix = Path(path).suffix.lower()
    if suffix in (".las", ".laz"):
        return _las.read_las_crs(Path(path))
    if suffix == ".e57":
        return _e57.read_e57_crs(Path(path))
    return None


def _read_single(p: Path, fmt: str, *, with_intensity: bool = True) -> tuple[RawCloud, str]:
    """Read a one-scan format; return the raw cloud and the format name for ``meta`` (LAS/LAZ
    without intensity when ``with_intensity`` is False)."""
    if fmt == "las":
        raw = _las.read_las(p, with_intensity=with_intensity)
        return raw, "laz" if raw.meta.get("compressed") else "las"
    if fmt == "ply":
        return _ply.read_ply(p), "ply"
    if fmt == "pcd":
        return _pcd.read_pcd(p), "pcd"
    return _xyz.read_text(p), "xyz"


def _check_index(scan_index: Optional[int]) -> Optional[int]:
    if scan_index is None:
        return None
    if isinstance(scan_index, bool):
        raise ParameterError(f"scan_index must be a whole number, got {scan_index!r}")
    try:
        value = operator.index(scan_index)
    except TypeError as exc:
        raise ParameterError(f"scan_index must be a whole number, got {scan_index!r}") from exc
    if value < 0:
        raise ParameterError(f"scan_index must be 0 or more, got {value}")
    return value


def _pick_e57_index(p: Path, count: int, index: Optional[int]) -> int:
    if count == 0:
        raise ScanReadError(f"{p}: the E57 file holds no scans")
    if index is None:
        if count > 1:
            raise ScanReadError(
                f"{p}: the E57 file holds {count} scans; give scan_index (0 to {count - 1}) or use read_scans"
            )
        return 0
    if index >= count:
        raise ScanReadError(
            f"{p}: the E57 file holds {count} scan(s); scan_index {index} is out of range 0 to {count - 1}"
        )
    return index


def _position(scanner_position: Optional[Sequence[float] | np.ndarray]) -> Optional[np.ndarray]:
    if scanner_position is None:
        return None
    try:
        pos = np.asarray(scanner_position, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"scanner_position must be three numbers, got {scanner_position!r}") from exc
    if pos.shape != (3,) or not np.isfinite(pos).all():
        raise ParameterError(f"scanner_position must be three finite numbers, got {scanner_position!r}")
    return pos


# --------------------------------------------------------------------------------------- writing

#: ``write_scan``'s default CRS: the scan's own when it is written where it is, none when moved.
_SCAN_CRS = object()


def write_scan(scan: Scan, path: PathLike, *, matrix: Optional[np.ndarray] = None, crs=_SCAN_CRS) -> None:
    """Write a scan's file coordinates (metres), optionally transformed, with its intensity.

    ``matrix`` (4x4) maps file coordinates to output coordinates: ``p_out = matrix @ p_file``
    (homogeneous). The format follows the suffix (see :data:`SUPPORTED_WRITE_SUFFIXES`); ``.e57``
    writes one scan with an identity pose (the points are already transformed). ``crs`` (a
    :class:`~forestreg.engine.io.crs.Crs`, or None) is the CRS of the output coordinates, stored
    by LAS/LAZ/COPC; by default the scan's own without ``matrix`` and none with one (the moved
    points are in another frame: the caller names its CRS).

    Raises
    ------
    ScanWriteError
        Unsupported suffix, missing folder, or the write failed (the target is left untouched).
    ParameterError
        ``matrix`` is not a finite 4x4 matrix.
    """
    m = as_matrix(matrix)
    local, shift = scan.points, scan.origin_shift
    if m is not None:
        rotation, translation = m[:3, :3], m[:3, 3]
        moved_shift = rotation @ shift + translation
        shift = np.round(moved_shift)
        # local coordinates stay small; the large part of the transform goes into the shift
        local = local @ rotation.T + (moved_shift - shift)
    if crs is _SCAN_CRS:
        crs = scan.meta.get("crs") if m is None else None
    _write(
        Path(path),
        PointsToWrite(local, np.asarray(shift, dtype=np.float64), scan.intensity, None, scan.name or "scan", crs),
    )


def write_points(
    path: PathLike,
    points: np.ndarray,
    *,
    intensity: Optional[np.ndarray] = None,
    scan_id: Optional[np.ndarray] = None,
    origin_shift: Optional[np.ndarray] = None,
    crs=None,
) -> None:
    """Write raw points; the format follows the suffix.

    Parameters
    ----------
    points : (N, 3) coordinates in metres, relative to ``origin_shift`` (written coordinates are
        ``points + origin_shift``); without ``origin_shift`` they are the file coordinates.
    intensity : optional (N,) values (written as float in PLY/text, mapped to uint16 in LAS).
    scan_id : optional (N,) whole numbers 0..65535: a ``scan_id`` extra dimension (LAS/LAZ), a
        property (PLY), a column (text); in E57 each id becomes its own scan.
    origin_shift : optional (3,) shift, metres.
    crs : the coordinate reference system of the written coordinates
        (:class:`~forestreg.engine.io.crs.Crs`), stored by LAS/LAZ/COPC; None: local.

    Raises
    ------
    ScanWriteError, ParameterError
        As :func:`write_scan`; also for empty or non-finite points and bad column lengths.
    """
    pts, inten, ids = _checked_columns(path, points, intensity, scan_id)
    if len(pts) == 0:
        raise ParameterError(f"{path}: there are no points to write")
    _write(Path(path), PointsToWrite(pts, _checked_shift(origin_shift), inten, ids, Path(path).stem, crs))


def write_point_chunks(
    path: PathLike,
    chunks: Iterable[tuple[np.ndarray, Optional[np.ndarray], Optional[np.ndarray]]],
    *,
    bounds: tuple[np.ndarray, np.ndarray],
    origin_shift: Optional[np.ndarray] = None,
    with_intensity: bool = True,
    with_scan_id: bool = False,
    crs=None,
) -> int:
    """Write a cloud that arrives in chunks (e.g. one registered scan at a time) into one file.

    LAS/LAZ are written chunk by chunk (:class:`~forestreg.engine.io.las.LasChunkWriter`), so
    only one chunk is in memory at a time; ``*.copc.laz`` is written as COPC out of core
    (:class:`~forestreg.engine.io.copc.CopcWriter`: the points are spilled into an octree of
    temporary files beside the target, then written node by node); other formats gather the
    chunks and write them as :func:`write_points` does. Written through a temporary file like every writer: a failure
    leaves no partial file and the previous file intact.

    Parameters
    ----------
    chunks : iterable of ``(points, intensity, scan_id)``: (N, 3) coordinates in metres relative
        to ``origin_shift`` (file coordinates without it), optional (N,) intensities and (N,)
        scan ids 0..65535 (required when ``with_scan_id``).
    bounds : ``(lo, hi)`` (3,) each: bounds that hold every point to come, relative to
        ``origin_shift`` like the points (generous bounds are fine).
    with_intensity : write intensities (chunks without them get 0).
    crs : the coordinate reference system of the written coordinates
        (:class:`~forestreg.engine.io.crs.Crs`), stored by LAS/LAZ/COPC; None: local.

    Returns the number of points written. Raises as :func:`write_points`; no points at all is a
    :class:`ParameterError`.
    """
    target = Path(path)
    shift = _checked_shift(origin_shift)
    if target.suffix.lower() not in (".las", ".laz"):
        parts = [_checked_columns(path, *chunk) for chunk in chunks]
        if not parts or not sum(len(p) for p, _, _ in parts):
            raise ParameterError(f"{path}: there are no points to write")
        if with_scan_id and any(d is None for _, _, d in parts):
            raise ParameterError(f"{path}: every chunk needs a scan_id per point")
        keep = with_intensity and all(i is not None for _, i, _ in parts)
        write_points(
            target,
            np.concatenate([p for p, _, _ in parts]),
            origin_shift=shift,
            intensity=np.concatenate([i for _, i, _ in parts]) if keep else None,
            scan_id=np.concatenate([d for _, _, d in parts]) if with_scan_id else None,
            crs=crs,
        )
        return int(sum(len(p) for p, _, _ in parts))
    lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) + shift for b in bounds)
    written = [0]

    def writer(tmp: Path):
        if _copc.is_copc_path(target):
            return _copc.CopcWriter(tmp, lo, hi, with_scan_id=with_scan_id, label=str(path), crs=crs)
        return _las.LasChunkWriter(
            tmp, lo, hi, compress=target.suffix.lower() == ".laz", with_scan_id=with_scan_id, crs=crs
        )

    def body(tmp: Path) -> None:
        with writer(tmp) as out:
            for chunk in chunks:
                pts, inten, ids = _checked_columns(path, *chunk)
                if with_scan_id and ids is None and len(pts):
                    raise ParameterError(f"{path}: every chunk needs a scan_id per point")
                out.write(pts, shift, intensity=inten if with_intensity else None, scan_id=ids)
            written[0] = out.count
            if not written[0]:
                raise ParameterError(f"{path}: there are no points to write")

    _atomic(target, body)
    return written[0]


def _checked_shift(origin_shift: Optional[np.ndarray]) -> np.ndarray:
    """``origin_shift`` as three finite floats (zeros when None); ParameterError otherwise."""
    shift = np.zeros(3) if origin_shift is None else np.asarray(origin_shift, dtype=np.float64).reshape(-1)
    if shift.shape != (3,) or not np.isfinite(shift).all():
        raise ParameterError(f"origin_shift must be three finite numbers, got {origin_shift!r}")
    return shift


def _checked_columns(
    path: PathLike,
    points: np.ndarray,
    intensity: Optional[np.ndarray] = None,
    scan_id: Optional[np.ndarray] = None,
) -> tuple[np.ndarray, Optional[np.ndarray], Optional[np.ndarray]]:
    """Points (N, 3) finite, intensity (N,) and scan ids (N,) whole numbers 0..65535 as uint16;
    ParameterError naming ``path`` otherwise."""
    pts = as_points(points)
    if not np.isfinite(pts).all():
        raise ParameterError(
            f"{path}: {int((~np.isfinite(pts).all(axis=1)).sum())} points have NaN or infinite coordinates"
        )
    inten = as_column(intensity, len(pts), "intensity")
    ids = as_column(scan_id, len(pts), "scan_id")
    if ids is not None:
        ids_f = ids.astype(np.float64)
        if (
            not np.isfinite(ids_f).all()
            or (ids_f < 0).any()
            or (ids_f > 65535).any()
            or (ids_f != np.round(ids_f)).any()
        ):
            raise ParameterError("scan_id must hold whole numbers 0..65535")
        ids = ids_f.astype(np.uint16)
    return pts, inten, ids


def write_e57(path: PathLike, scans: list[Scan], poses: Optional[list[Optional[np.ndarray]]] = None) -> None:
    """Write scans into one E57 file, one data3D entry each.

    Each entry holds the scan's file coordinates (its own coordinates; 0.1 mm scaled integers, so
    georeferenced values keep their precision) and intensity, under the scan's name, with the pose
    ``poses[i]`` if given, else ``scan.pose``, else identity. A pose must be rigid (E57 stores a
    quaternion and a translation).

    Raises
    ------
    ScanWriteError
        No scans, a non-rigid pose, a wrong suffix, or the write failed (target left untouched).
    ParameterError
        ``poses`` does not match ``scans`` or a pose is not a finite 4x4 matrix.
    """
    target = Path(path)
    scans = list(scans)
    if not scans:
        raise ScanWriteError(f"cannot write {target}: no scans given")
    if poses is not None and len(poses) != len(scans):
        raise ParameterError(f"{len(poses)} poses for {len(scans)} scans")
    entries = []
    for i, scan in enumerate(scans):
        given = poses[i] if poses is not None else None
        pose = as_matrix(given, f"pose {i}") if given is not None else scan.pose
        pose = np.eye(4) if pose is None else np.asarray(pose, dtype=np.float64)
        _e57.check_rigid(pose, f"pose of scan {i} ({scan.name})")
        entries.append(_e57.E57Entry(scan.points, scan.origin_shift, scan.intensity, pose, scan.name or f"scan {i}"))
    if target.suffix.lower() != ".e57":
        raise ScanWriteError(f"cannot write {target}: write_e57 writes .e57 files only")
    _atomic(target, lambda tmp: _e57.write_e57_file(tmp, entries))


def _write(target: Path, cloud: PointsToWrite) -> None:
    """Write points ``cloud.local + cloud.shift`` in the format the suffix of ``target`` names."""
    suffix = target.suffix.lower()
    if _copc.is_copc_path(target):

        def body(tmp: Path) -> None:
            _copc.write_copc(tmp, cloud, label=str(target))
    elif suffix in (".las", ".laz"):

        def body(tmp: Path) -> None:
            _las.write_las(tmp, cloud, compress=suffix == ".laz")
    elif suffix == ".ply":

        def body(tmp: Path) -> None:
            _ply.write_ply(tmp, cloud)
    elif suffix in (".xyz", ".txt"):

        def body(tmp: Path) -> None:
            _xyz.write_text(tmp, cloud)
    elif suffix == ".e57":
        entries = _e57_entries(cloud)

        def body(tmp: Path) -> None:
            _e57.write_e57_file(tmp, entries)
    else:
        raise ScanWriteError(
            f"cannot write {target}: unsupported suffix {target.suffix!r} (use {', '.join(SUPPORTED_WRITE_SUFFIXES)})"
        )
    _atomic(target, body)


def _e57_entries(cloud: PointsToWrite) -> list[_e57.E57Entry]:
    """One E57 entry for the cloud, or one per scan id when it has them."""
    local, shift, intensity, scan_id, name = cloud.local, cloud.shift, cloud.intensity, cloud.scan_id, cloud.name
    if scan_id is None:
        return [_e57.E57Entry(local, shift, intensity, np.eye(4), name)]
    entries = []
    for value in np.unique(scan_id):
        sel = scan_id == value
        entries.append(
            _e57.E57Entry(local[sel], shift, None if intensity is None else intensity[sel], np.eye(4), f"scan {value}")
        )
    return entries


def _atomic(target: Path, body) -> None:
    """Run ``body(tmp)`` inside :func:`atomic_path`; wrap library and OS errors in ScanWriteError."""
    try:
        with atomic_path(target) as tmp:
            body(tmp)
            _set_mode(tmp, target)
    except ForestregError:
        raise
    except Exception as exc:
        detail = str(exc).strip().splitlines()
        raise ScanWriteError(f"cannot write {target}: {detail[0] if detail else type(exc).__name__}") from exc


def _set_mode(tmp: Path, target: Path) -> None:
    """Give the new file the target's permissions, or the usual ones (``0o666`` minus umask):
    :func:`tempfile.mkstemp` creates it readable by its owner only."""
    try:
        mode = target.stat().st_mode & 0o7777
    except OSError:
        mode = 0o666 & ~_umask()
    os.chmod(tmp, mode)


def _umask() -> int:
    """The process umask, read without changing it where the system allows (Linux)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    umask = os.umask(0o022)
    os.umask(umask)
    return umask
