"""Shared pieces of the readers and writers: the raw cloud a reader returns, scan building, checks.

A reader returns :class:`RawCloud` objects in *file units* (whatever the file holds); turning one
into a :class:`~forestreg.engine.core.scan.Scan` (unit scale, scanner position, validation) happens
once, in :func:`build_scan`.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..core.errors import ParameterError, ScanDataError, ScanReadError
from ..core.scan import Scan

PathLike = str | os.PathLike[str]


@dataclass
class RawCloud:
    """Points as read from a file, before unit scaling and validation.

    Attributes
    ----------
    points : (N, 3) float64 file coordinates, file units.
    intensity : optional (N,) intensities as stored (any numeric dtype).
    name : scan name stored in the file (E57), else ``None`` (the file stem is used).
    pose : optional 4x4 pose mapping these coordinates into the file's common frame (file units).
    scanner_position : optional (3,) scanner position in these coordinates (file units).
    meta : facts about reading (format, counts, columns, ...).
    """

    points: np.ndarray
    intensity: Optional[np.ndarray] = None
    name: Optional[str] = None
    pose: Optional[np.ndarray] = None
    scanner_position: Optional[np.ndarray] = None
    meta: dict[str, Any] = field(default_factory=dict)


_ALLOCATOR_TUNED = False


@dataclass(frozen=True)
class PointsToWrite:
    """Points a writer puts into a file: the file coordinates are ``local + shift`` (metres).

    Attributes
    ----------
    local : (N, 3) float64 coordinates relative to ``shift``, metres.
    shift : (3,) float64 origin shift, metres.
    intensity : optional (N,) intensities.
    scan_id : optional (N,) uint16 scan indices.
    name : scan name (formats that store one, E57).
    crs : the coordinate reference system of the written coordinates
        (:class:`~forestreg.engine.io.crs.Crs`; LAS/LAZ/COPC store it), None when local.
    """

    local: np.ndarray
    shift: np.ndarray
    intensity: Optional[np.ndarray] = None
    scan_id: Optional[np.ndarray] = None
    name: str = "scan"
    crs: Any = None


def tune_allocator(threshold_bytes: int = 4 << 20) -> None:
    """Make freed large arrays go back to the operating system at once (glibc only; once per
    process; a no-op elsewhere or when ``MALLOC_MMAP_THRESHOLD_`` is set by the user).

    glibc raises its mmap threshold up to 32 MB after large blocks are freed, so the 10-30 MB
    temporaries of a point-cloud pipeline end up recycled inside the heap and per-thread arenas and
    the process keeps hundreds of MB it no longer uses. A fixed threshold sends every block above
    ``threshold_bytes`` to mmap. Measured on a pair of 3 M-point scans: peak 1,267 MB untuned
    (with the dynamic threshold), 768 MB at 16 MB, 652 MB at 4 MB, 651 MB at 1 MB; the wall time
    grows as the threshold falls (page faults on fresh mappings): 4 MB is within ~6 % of 16 MB.
    """
    global _ALLOCATOR_TUNED
    if _ALLOCATOR_TUNED:
        return
    _ALLOCATOR_TUNED = True
    if not sys.platform.startswith("linux") or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None)
        m_mmap_threshold = -3  # glibc's M_MMAP_THRESHOLD
        libc.mallopt(ctypes.c_int(m_mmap_threshold), ctypes.c_int(int(threshold_bytes)))
    except (OSError, AttributeError):  # not glibc (musl, ...): nothing to tune
        pass


def read_text_lines(path: PathLike, error: type[Exception], what: str) -> tuple[Path, list[tuple[int, str]]]:
    """The lines of a small text table (UTF-8, a byte-order mark allowed) that are neither blank
    nor ``#`` comments, each with its 1-based line number. A missing or unreadable file raises
    ``error`` with one line naming ``what`` (e.g. "target file") and the path."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError as exc:
        raise error(f"{what} {p} does not exist") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{what} {p} cannot be read: {getattr(exc, 'strerror', None) or exc}") from exc
    return p, [
        (i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip() and not line.lstrip().startswith("#")
    ]


def check_unit_scale(unit_scale: float) -> float:
    """Return ``unit_scale`` as a float, or raise :class:`ParameterError` unless finite and > 0."""
    try:
        value = float(unit_scale)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"unit_scale must be a positive number, got {unit_scale!r}") from exc
    if not math.isfinite(value) or value <= 0.0:
        raise ParameterError(f"unit_scale must be a positive number, got {unit_scale!r}")
    return value


def check_readable(path: PathLike) -> Path:
    """Return ``path`` as a :class:`Path` if it is an existing, non-empty, readable regular file.

    Raises
    ------
    ScanReadError
        Missing, a folder, a pipe or a device (opening one would wait for a writer), empty, or not
        readable.
    """
    p = Path(path)
    if not p.exists():
        raise ScanReadError(f"{p}: no such file")
    if p.is_dir():
        raise ScanReadError(f"{p}: is a folder, not a scan file")
    if not p.is_file():
        raise ScanReadError(f"{p}: is not a regular file (a pipe, socket or device): save the points to a file first")
    try:
        size = p.stat().st_size
        with open(p, "rb"):
            pass
    except OSError as exc:
        raise ScanReadError(f"{p}: cannot be opened ({exc.strerror or exc})") from exc
    if size == 0:
        raise ScanReadError(f"{p}: the file is empty (0 bytes)")
    return p


def build_scan(
    raw: RawCloud,
    path: Path,
    *,
    fmt: str,
    unit_scale: float,
    scanner_position: Optional[np.ndarray] = None,
    label: Optional[str] = None,
) -> Scan:
    """Scale a raw cloud to metres and validate it into a :class:`Scan`.

    ``scanner_position`` (file coordinates, file units) overrides the position the reader found;
    ``unit_scale`` multiplies coordinates, scanner position and pose translation.
    ``label`` names the scan in error messages (default: the file name).
    """
    tune_allocator()
    where = label or path.name
    if len(raw.points) == 0:
        raise ScanReadError(f"{path}: {'' if label is None else label + ': '}contains no points")
    points = raw.points if unit_scale == 1.0 else raw.points * unit_scale
    scanner = scanner_position if scanner_position is not None else raw.scanner_position
    if scanner is not None:
        scanner = np.asarray(scanner, dtype=np.float64).reshape(-1) * unit_scale
    pose = None
    if raw.pose is not None:
        pose = np.array(raw.pose, dtype=np.float64)
        pose[:3, 3] *= unit_scale
    meta = {"format": fmt, "unit_scale": unit_scale, **raw.meta}
    try:
        return Scan.from_points(
            points,
            scanner_position=scanner,
            intensity=raw.intensity,
            source=path,
            name=raw.name,
            pose=pose,
            meta=meta,
            # LAS/LAZ points are a fresh array of the reader's; scaled points a fresh product
            take_ownership=fmt in ("las", "laz") or points is not raw.points,
        )
    except ScanDataError as exc:
        message = str(exc)
        if label is None and message.startswith(path.name):
            raise
        if raw.name and message.startswith(f"{raw.name}: "):
            message = message[len(raw.name) + 2 :]
        raise ScanDataError(f"{path.name}, {where}: {message}" if label else f"{path.name}: {message}") from exc


def as_points(points: np.ndarray, what: str = "points") -> np.ndarray:
    """Return ``points`` as a float64 (N, 3) array or raise :class:`ParameterError`."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ParameterError(f"{what} must be an (N, 3) array, got shape {arr.shape}")
    return arr


def as_column(values: Optional[np.ndarray], n: int, what: str) -> Optional[np.ndarray]:
    """Return an optional per-point column as a 1-D array of length ``n``, or raise."""
    if values is None:
        return None
    arr = np.asarray(values).reshape(-1)
    if len(arr) != n:
        raise ParameterError(f"{what} has {len(arr)} values for {n} points")
    return arr


def as_matrix(matrix: Optional[np.ndarray], what: str = "matrix") -> Optional[np.ndarray]:
    """Return an optional 4x4 finite float64 matrix, or raise :class:`ParameterError`."""
    if matrix is None:
        return None
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ParameterError(f"{what} must be a finite 4x4 matrix, got shape {m.shape}")
    return m


#: a coordinate step of a 32-bit float file (file units) from which a warning is logged: 1 mm
FLOAT32_STEP_WARN = 0.001
_float32_warned: set = set()
_float32_lock = threading.Lock()


def float32_precision(path: Path, points: np.ndarray, meta: dict[str, Any]) -> None:
    """For a file storing x, y, z as 32-bit floats: the step between neighbouring values at its
    largest coordinate (``meta["float32_step"]``, file units) and, when it is 1 mm or more, one
    warning naming the precision lost in the file (a UTM easting of 5.2e6 m in float32 moves in
    0.5 m steps: no registration can be finer than the file). Logged once per file."""
    if not len(points):
        return
    big = float(np.nanmax(np.abs(points))) if np.isfinite(points).any() else 0.0
    step = float(np.spacing(np.float32(big)))
    meta["float32_step"] = step
    if step < FLOAT32_STEP_WARN:
        return
    key = str(Path(path).resolve())
    with _float32_lock:
        if key in _float32_warned:
            return
        _float32_warned.add(key)
    logging.getLogger("forestreg.io").warning(
        "%s stores x, y, z as 32-bit floats: at coordinates of %.3g its values are only %.3g apart (%.3g m in a file "
        "in metres); that precision is lost in the file and no result can be finer (write it with 64-bit floats, or "
        "shifted near 0)",
        Path(path).name,
        big,
        step,
        step,
    )
