"""PCD reading: ASCII and binary with an own parser; binary_compressed through open3d.

Points with NaN coordinates (organised clouds mark "no return" so) are dropped here and counted in
``meta["dropped_invalid"]``, so they do not count as damage later.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import ScanReadError
from .base import RawCloud, float32_precision
from .ply import INTENSITY_NAMES

_MAX_HEADER = 1 << 16
_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


def _parse_header(path: Path) -> tuple[dict[str, list[str]], int]:
    """Return the header entries (key -> words) and the byte length of the header."""
    with open(path, "rb") as fh:
        raw = fh.read(_MAX_HEADER)
    entries: dict[str, list[str]] = {}
    pos = 0
    while pos < len(raw):
        nl = raw.find(b"\n", pos)
        if nl < 0:
            raise ScanReadError(f"{path}: PCD header is incomplete; the file is truncated or corrupt")
        line = raw[pos:nl].decode("ascii", errors="replace").strip()
        pos = nl + 1
        if not line or line.startswith("#"):
            continue
        words = line.split()
        key = words[0].upper()
        if key not in _KEYS:
            raise ScanReadError(f"{path}: PCD header line {line!r} is not understood")
        entries[key] = words[1:]
        if key == "DATA":
            return entries, pos
    raise ScanReadError(f"{path}: PCD header has no DATA line; the file is truncated or corrupt")


def _dtype(path: Path, entries: dict[str, list[str]]) -> np.dtype:
    fields = entries.get("FIELDS")
    sizes = entries.get("SIZE")
    types = entries.get("TYPE")
    if not fields or not sizes or not types:
        raise ScanReadError(f"{path}: PCD header lacks FIELDS, SIZE or TYPE")
    counts = entries.get("COUNT") or ["1"] * len(fields)
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise ScanReadError(f"{path}: PCD header FIELDS, SIZE, TYPE and COUNT differ in length")
    parts = []
    for k, (name, size, kind, count) in enumerate(zip(fields, sizes, types, counts)):
        code = {"F": "f", "I": "i", "U": "u"}.get(kind.upper())
        if code is None or size not in ("1", "2", "4", "8"):
            raise ScanReadError(f"{path}: PCD field {name!r} has an unknown type {kind}{size}")
        n = int(count)
        unique = name if name != "_" else f"_pad{k}"
        parts.append((unique, f"<{code}{size}", (n,)) if n > 1 else (unique, f"<{code}{size}"))
    return np.dtype(parts)


def read_pcd(path: Path) -> RawCloud:
    """Read a PCD file: x, y, z as float64 (file units) and intensity if present."""
    entries, header_len = _parse_header(path)
    dtype = _dtype(path, entries)
    names = list(dtype.names or ())
    for axis in "xyz":
        if axis not in names:
            raise ScanReadError(f"{path}: PCD file has no '{axis}' field")
    try:
        if "POINTS" in entries:
            count = int(entries["POINTS"][0])
        else:
            count = int(entries["WIDTH"][0]) * int(entries["HEIGHT"][0])
    except (KeyError, IndexError, ValueError) as exc:
        raise ScanReadError(f"{path}: PCD header has no valid POINTS count") from exc
    if count == 0:
        raise ScanReadError(f"{path}: contains no points (PCD POINTS 0)")
    kind = (entries["DATA"] or [""])[0].lower()
    float32_meta: dict = {}
    if kind == "ascii":
        # the text holds the digits as written: kept as float64 even where the header says 4 bytes
        wide = np.dtype([(n, (np.float64, dtype[n].shape) if dtype[n].kind == "f" else dtype[n]) for n in dtype.names])
        data = _read_ascii(path, wide, count, header_len)
        xyz = np.column_stack([data[a] for a in "xyz"]).astype(np.float64)
        intensity = _intensity(data, names)
    elif kind == "binary":
        if path.stat().st_size - header_len < count * dtype.itemsize:
            raise ScanReadError(
                f"{path}: is truncated: the PCD header announces {count:,} points, the data are shorter"
            )
        data = np.fromfile(path, dtype=dtype, count=count, offset=header_len)
        xyz = np.column_stack([data[a] for a in "xyz"]).astype(np.float64)
        intensity = _intensity(data, names)
        if any(dtype[a].itemsize == 4 and dtype[a].kind == "f" for a in "xyz"):
            float32_precision(path, xyz[np.isfinite(xyz).all(axis=1)], float32_meta)
    elif kind == "binary_compressed":
        xyz, intensity = _read_with_open3d(path)
    else:
        raise ScanReadError(f"{path}: PCD data kind {kind!r} is not ascii, binary or binary_compressed")
    finite = np.isfinite(xyz).all(axis=1)
    dropped = int(len(xyz) - finite.sum())
    if dropped:
        xyz = xyz[finite]
        intensity = None if intensity is None else intensity[finite]
    meta = {"pcd_data": kind, "point_count_in_file": count, "dropped_invalid": dropped, **float32_meta}
    if "VIEWPOINT" in entries:
        meta["pcd_viewpoint"] = [float(v) for v in entries["VIEWPOINT"]]
    return RawCloud(points=xyz, intensity=intensity, meta=meta)


def _intensity(data: np.ndarray, names: list[str]) -> Optional[np.ndarray]:
    lower = {n.lower(): n for n in names}
    for candidate in INTENSITY_NAMES:
        if candidate in lower and data.dtype[lower[candidate]].shape == ():
            return np.asarray(data[lower[candidate]])
    return None


def _read_ascii(path: Path, dtype: np.dtype, count: int, header_len: int) -> np.ndarray:
    try:
        with open(path, "rb") as fh:
            fh.seek(header_len)
            flat = np.loadtxt(fh, dtype=np.float64, max_rows=count, ndmin=2, encoding="latin-1")
    except ValueError as exc:
        raise ScanReadError(f"{path}: PCD point lines cannot be parsed ({exc})") from exc
    width = sum(int(np.prod(dtype[n].shape)) if dtype[n].shape else 1 for n in dtype.names or ())
    if len(flat) < count:
        raise ScanReadError(
            f"{path}: is truncated: the PCD header announces {count:,} points, the file holds {len(flat):,}"
        )
    if flat.shape[1] < width:
        raise ScanReadError(f"{path}: PCD point lines have {flat.shape[1]} values, the header names {width}")
    out = np.empty(count, dtype=dtype)
    col = 0
    for name in dtype.names or ():
        n = int(np.prod(dtype[name].shape)) if dtype[name].shape else 1
        out[name] = flat[:, col] if n == 1 else flat[:, col : col + n]
        col += n
    return out


def _read_with_open3d(path: Path) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """binary_compressed (LZF) PCD via open3d's tensor reader, which keeps intensity."""
    from ..core.imports import import_open3d

    o3d = import_open3d()

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.t.io.read_point_cloud(str(path))
    if cloud.is_empty() or "positions" not in cloud.point:
        raise ScanReadError(f"{path}: compressed PCD data cannot be read; the file is truncated or corrupt")
    xyz = cloud.point.positions.numpy().astype(np.float64)
    intensity = None
    for name in INTENSITY_NAMES:
        if name in cloud.point:
            intensity = cloud.point[name].numpy().reshape(-1)
            break
    return xyz, intensity
