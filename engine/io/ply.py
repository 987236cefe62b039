"""PLY reading (ASCII and binary, own parser) and writing (binary little-endian).

Only the ``vertex`` element is read: x, y, z and an intensity-like scalar if present
(``intensity``, ``scalar_intensity``, ``reflectance``, ... any case).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import ScanReadError
from .base import PointsToWrite, RawCloud, float32_precision

_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
#: Property names taken as intensity, in order of preference (compared lower-case).
INTENSITY_NAMES = (
    "intensity",
    "scalar_intensity",
    "reflectance",
    "scalar_reflectance",
    "amplitude",
    "scalar_amplitude",
)
_MAX_HEADER = 1 << 20


class _Element:
    def __init__(self, name: str, count: int) -> None:
        self.name = name
        self.count = count
        self.props: list[tuple[str, str]] = []  # (name, numpy type code)
        self.has_list = False


def _parse_header(path: Path) -> tuple[str, list[_Element], int]:
    """Return ``(format, elements, header_length_bytes)``."""
    with open(path, "rb") as fh:
        raw = fh.read(_MAX_HEADER)
    end = raw.find(b"end_header")
    if end < 0:
        raise ScanReadError(f"{path}: PLY header has no 'end_header'; the file is truncated or corrupt")
    nl = raw.find(b"\n", end)
    if nl < 0:
        raise ScanReadError(f"{path}: PLY file ends right after its header; it holds no points")
    header_len = nl + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt: Optional[str] = None
    elements: list[_Element] = []
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append(_Element(words[1], int(words[2])))
            elif words[0] == "property":
                if not elements:
                    raise ValueError("property before any element")
                if words[1] == "list":
                    elements[-1].has_list = True
                    elements[-1].props.append((words[4], "list"))
                else:
                    elements[-1].props.append((words[2], _TYPES[words[1]]))
        except (IndexError, KeyError, ValueError) as exc:
            raise ScanReadError(f"{path}: PLY header line {line.strip()!r} is not understood") from exc
    if fmt not in _FORMATS:
        raise ScanReadError(f"{path}: PLY format {fmt!r} is not ascii or binary")
    return fmt, elements, header_len


def read_ply(path: Path) -> RawCloud:
    """Read the vertices of a PLY file: x, y, z (float64, file units) and intensity if present."""
    fmt, elements, header_len = _parse_header(path)
    vertex_at = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if vertex_at is None:
        raise ScanReadError(f"{path}: PLY file has no 'vertex' element")
    vertex = elements[vertex_at]
    names = [n for n, _ in vertex.props]
    for axis in "xyz":
        if axis not in names:
            raise ScanReadError(f"{path}: PLY vertices have no '{axis}' property")
    if vertex.has_list:
        raise ScanReadError(f"{path}: PLY vertices with list properties are not supported")
    if vertex.count == 0:
        raise ScanReadError(f"{path}: contains no points (PLY vertex count 0)")
    if fmt == "ascii":
        data = _read_ascii(path, elements[:vertex_at], vertex, header_len)
    else:
        data = _read_binary(path, elements[:vertex_at], vertex, header_len, _FORMATS[fmt])
    points = np.empty((vertex.count, 3), dtype=np.float64)
    for k, axis in enumerate("xyz"):
        points[:, k] = data[axis]
    intensity = None
    lower = {n.lower(): n for n in names}
    for candidate in INTENSITY_NAMES:
        if candidate in lower:
            intensity = np.asarray(data[lower[candidate]])
            break
    meta = {"ply_format": fmt, "point_count_in_file": vertex.count}
    if fmt != "ascii" and any(t == "f4" for n, t in vertex.props if n in ("x", "y", "z")):
        float32_precision(path, points, meta)
    return RawCloud(points=points, intensity=intensity, meta=meta)


def _read_binary(path: Path, before: list[_Element], vertex: _Element, header_len: int, endian: str) -> np.ndarray:
    skip = 0
    for el in before:
        if el.has_list:
            raise ScanReadError(f"{path}: PLY element '{el.name}' with lists precedes the vertices; not supported")
        skip += el.count * int(sum(np.dtype(t).itemsize for _, t in el.props))
    dtype = np.dtype([(n, endian + t) for n, t in vertex.props])
    try:
        data = np.fromfile(path, dtype=dtype, count=vertex.count, offset=header_len + skip)
    except (OSError, ValueError) as exc:
        raise ScanReadError(
            f"{path}: PLY vertex data cannot be read ({exc}); the file is truncated or corrupt"
        ) from exc
    if len(data) < vertex.count:
        raise ScanReadError(
            f"{path}: is truncated: the PLY header announces {vertex.count:,} vertices, the file holds {len(data):,}"
        )
    return data


def _read_ascii(path: Path, before: list[_Element], vertex: _Element, header_len: int) -> np.ndarray:
    skip_lines = sum(el.count for el in before)
    # the text holds the digits as written: kept as float64 even where the header says float
    dtype = np.dtype([(n, "f8" if t == "f4" else t) for n, t in vertex.props])
    try:
        with open(path, "rb") as fh:
            fh.seek(header_len)
            for _ in range(skip_lines):
                fh.readline()
            flat = np.loadtxt(fh, dtype=np.float64, max_rows=vertex.count, ndmin=2, encoding="latin-1")
    except ValueError as exc:
        raise ScanReadError(f"{path}: PLY vertex lines cannot be parsed ({exc})") from exc
    if len(flat) < vertex.count:
        raise ScanReadError(
            f"{path}: is truncated: the PLY header announces {vertex.count:,} vertices, the file holds {len(flat):,}"
        )
    if flat.shape[1] < len(vertex.props):
        raise ScanReadError(
            f"{path}: PLY vertex lines have {flat.shape[1]} values, the header names {len(vertex.props)}"
        )
    data = np.empty(vertex.count, dtype=dtype)
    for k, (name, _) in enumerate(vertex.props):
        data[name] = flat[:, k]
    return data


def write_ply(tmp: Path, cloud: PointsToWrite) -> None:
    """Write points ``cloud.local + cloud.shift`` as binary little-endian PLY: double x, y, z;
    float ``intensity``; ushort ``scan_id``."""
    local, shift, intensity, scan_id = cloud.local, cloud.shift, cloud.intensity, cloud.scan_id
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by forestreg",
        f"element vertex {len(local)}",
        "property double x",
        "property double y",
        "property double z",
    ]
    if intensity is not None:
        fields.append(("intensity", "<f4"))
        header.append("property float intensity")
    if scan_id is not None:
        fields.append(("scan_id", "<u2"))
        header.append("property ushort scan_id")
    header.append("end_header")
    data = np.empty(len(local), dtype=np.dtype(fields))
    for k, axis in enumerate("xyz"):
        data[axis] = local[:, k] + shift[k]
    if intensity is not None:
        data["intensity"] = intensity
    if scan_id is not None:
        data["scan_id"] = scan_id
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        data.tofile(fh)
