"""ASCII point lists (XYZ, TXT, CSV, PTS, ASC): reading and writing.

Reading is tolerant: whitespace, comma or semicolon separated columns ``x y z [intensity ...]``;
leading header lines of words (a header naming columns is honoured, e.g. ``//X Y Z Intensity``);
a PTS point-count line; ``#`` and ``//`` comments. The fast path is :func:`numpy.loadtxt` (a C
parser since numpy 1.23: about 0.4-0.7 s per million lines); a line-by-line parser takes over if a
file has ragged or damaged lines, skipping a few of them.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import ScanReadError
from .base import PointsToWrite, RawCloud

#: Lines searched for the first x y z row.
_HEADER_SCAN_LINES = 200
#: Largest fraction of lines the tolerant parser may skip before the file counts as damaged.
MAX_SKIPPED_FRACTION = 0.05
#: Header names taken as intensity (compared lower-case).
_INTENSITY_NAMES = (
    "intensity",
    "scalar_intensity",
    "i",
    "reflectance",
    "scalar_reflectance",
    "amplitude",
    "scalar_amplitude",
)
_SPLIT = re.compile(r"[\s,;]+")
#: A number written with a decimal comma (1,25 or -3,5e2), as spreadsheets in many locales write
#: them, fields separated by semicolons.
_DECIMAL_COMMA = re.compile(r"[-+]?\d+(,\d+)?([eE][-+]?\d+)?")
#: The "delimiter" :func:`_layout` gives a file of such numbers.
_DECIMAL_COMMA_LAYOUT = "decimal comma"
_CHUNK_ROWS = 200_000


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def _words(line: str) -> list[str]:
    text = line.strip()
    for lead in ("//", "#"):
        if text.startswith(lead):
            text = text[len(lead) :]
    return [w for w in _SPLIT.split(text.strip()) if w]


def _layout(path: Path) -> tuple[int, Optional[str], int, list[str]]:
    """Find ``(lines_to_skip, delimiter, n_columns, header_names)`` from the first lines."""
    header: list[str] = []
    with open(path, "r", encoding="latin-1", newline=None) as fh:
        for index in range(_HEADER_SCAN_LINES):
            line = fh.readline()
            if not line:
                break
            stripped = line.strip()
            if not stripped or stripped.startswith("#") or stripped.startswith("//"):
                if stripped:
                    header = _words(stripped)
                continue
            words = _words(stripped)
            fields = [w.strip() for w in stripped.split(";")]
            if ";" in stripped and len(fields) >= 3 and all(_DECIMAL_COMMA.fullmatch(w) for w in fields if w):
                return index, _DECIMAL_COMMA_LAYOUT, len([w for w in fields if w]), header
            if len(words) >= 3 and all(_is_number(w) for w in words):
                if "," in stripped:
                    delimiter: Optional[str] = ","
                elif ";" in stripped:
                    delimiter = ";"
                else:
                    delimiter = None
                return index, delimiter, len(words), header
            header = words
    raise ScanReadError(
        f"{path}: no line with three numbers (x y z) in its first {_HEADER_SCAN_LINES} lines; "
        "it is not a text point list or it holds no points"
    )


def _columns(ncols: int, header: list[str]) -> tuple[list[int], Optional[int], str]:
    """Return the x, y, z column indices, the intensity column (or None) and how it was chosen."""
    names = [h.lower() for h in header]
    if len(names) >= 3 and {"x", "y", "z"} <= set(names):
        xyz = [names.index(a) for a in "xyz"]
        if max(xyz) < ncols:
            inten = next((names.index(n) for n in _INTENSITY_NAMES if n in names and names.index(n) < ncols), None)
            return xyz, inten, "header"
    if ncols == 6:  # x y z r g b or x y z nx ny nz: no intensity column
        return [0, 1, 2], None, "position"
    return [0, 1, 2], (3 if ncols >= 4 else None), "position"


def read_text(path: Path) -> RawCloud:
    """Read an ASCII point list: x, y, z as float64 (file units) and intensity if present."""
    skip, delimiter, ncols, header = _layout(path)
    xyz_cols, inten_col, chosen = _columns(ncols, header)
    usecols = xyz_cols + ([inten_col] if inten_col is not None else [])
    skipped = 0
    try:
        if delimiter == _DECIMAL_COMMA_LAYOUT:  # 0,132;18,645;3,971: the commas are decimal points
            with open(path, "r", encoding="latin-1", newline=None) as fh:
                table = np.loadtxt(
                    (line.replace(",", ".") for line in fh),
                    dtype=np.float64,
                    delimiter=";",
                    skiprows=skip,
                    usecols=usecols,
                    comments="#",
                    ndmin=2,
                )
        else:
            table = np.loadtxt(
                path,
                dtype=np.float64,
                delimiter=delimiter,
                skiprows=skip,
                usecols=usecols,
                comments="#",
                ndmin=2,
                encoding="latin-1",  # one comment string keeps the C fast path
            )
    except ValueError:
        if delimiter == _DECIMAL_COMMA_LAYOUT:
            raise ScanReadError(f"{path}: a line does not hold numbers with decimal commas separated by ';'") from None
        table, skipped = _read_tolerant(path, skip, usecols)
    if len(table) == 0:
        raise ScanReadError(f"{path}: contains no points")
    intensity = table[:, 3].astype(np.float32) if inten_col is not None else None
    meta = {
        "text_columns": ncols,
        "text_header_lines": skip,
        "intensity_column": inten_col,
        "columns_from": chosen,
        "skipped_lines": skipped,
        "point_count_in_file": len(table),
    }
    return RawCloud(points=np.ascontiguousarray(table[:, :3]), intensity=intensity, meta=meta)


def _read_tolerant(path: Path, skip: int, usecols: list[int]) -> tuple[np.ndarray, int]:
    """Line-by-line parse that skips damaged lines (at most :data:`MAX_SKIPPED_FRACTION`)."""
    rows: list[list[float]] = []
    bad = 0
    first_bad: Optional[int] = None
    need = max(usecols) + 1
    with open(path, "r", encoding="latin-1") as fh:
        for lineno, line in enumerate(fh, start=1):
            if lineno <= skip:
                continue
            text = line.strip()
            if not text or text.startswith("#") or text.startswith("//"):
                continue
            words = [w for w in _SPLIT.split(text) if w]
            try:
                if len(words) < need:
                    raise ValueError
                rows.append([float(words[c]) for c in usecols])
            except ValueError:
                bad += 1
                first_bad = first_bad or lineno
    total = len(rows) + bad
    if bad > MAX_SKIPPED_FRACTION * max(total, 1):
        raise ScanReadError(
            f"{path}: {bad:,} of {total:,} lines are not x y z numbers (first at line {first_bad}); "
            "the file is damaged or not a point list"
        )
    return np.array(rows, dtype=np.float64).reshape(-1, len(usecols)), bad


def write_text(tmp: Path, cloud: PointsToWrite) -> None:
    """Write ``x y z [intensity] [scan_id]`` lines (file coordinates ``cloud.local + cloud.shift``,
    0.1 mm steps) with a ``//x y z ...`` header line (CloudCompare's convention)."""
    local, shift, intensity, scan_id = cloud.local, cloud.shift, cloud.intensity, cloud.scan_id
    names = ["x", "y", "z"]
    row_format = "%.4f %.4f %.4f"
    columns = [local[:, 0] + shift[0], local[:, 1] + shift[1], local[:, 2] + shift[2]]
    if intensity is not None:
        names.append("intensity")
        row_format += " %.7g"
        columns.append(np.asarray(intensity, dtype=np.float64))
    if scan_id is not None:
        names.append("scan_id")
        row_format += " %d"
        columns.append(np.asarray(scan_id).astype(np.int64))
    row_format += "\n"
    with open(tmp, "w", encoding="ascii", newline="\n") as fh:
        fh.write("//" + " ".join(names) + "\n")
        for start in range(0, len(local), _CHUNK_ROWS):
            chunk = np.column_stack([c[start : start + _CHUNK_ROWS] for c in columns])
            fh.write((row_format * len(chunk)) % tuple(chunk.ravel().tolist()))
