"""Tables the product writes beside its results (VOPs of a pair registration and canopy keypoints
of a co-registration, always in the input file's own coordinates and units), and the tables of
trees it reads (:func:`read_trees_table`: a ``trees.csv`` of ``forestreg trees`` or a field sheet).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.atomic import write_text_atomic
from ..core.errors import ScanReadError
from ..core.transform import apply
from .sniff import column_key, table_delimiter

VOP_COLUMNS = ("id", "x", "y", "z", "radius_m", "support_points", "matched_with")
KEYPOINT_COLUMNS = ("id", "x", "y", "z", "peak_z", "cluster_size", "matched_with")


def write_vops_csv(
    path: str | Path,
    xy: np.ndarray,
    z: np.ndarray,
    to_file: np.ndarray,
    radius: np.ndarray,
    support: np.ndarray,
    matched_with: Sequence[int],
    *,
    unit_scale: float = 1.0,
) -> Path:
    """VOPs (levelled-frame ``xy``, ``z``, metres) as a CSV in file coordinates.

    ``to_file`` maps the levelled frame to the file frame in metres; ``unit_scale`` (metres per
    file unit) turns the coordinates back into the file's own unit. ``radius_m`` stays in metres.
    """
    pts = apply(to_file, np.column_stack([xy, z])) / unit_scale if len(xy) else np.zeros((0, 3))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(VOP_COLUMNS)
    for k in range(len(xy)):
        w.writerow(
            [
                k,
                f"{pts[k, 0]:.4f}",
                f"{pts[k, 1]:.4f}",
                f"{pts[k, 2]:.4f}",
                f"{radius[k]:.3f}",
                int(support[k]),
                "" if matched_with[k] < 0 else int(matched_with[k]),
            ]
        )
    write_text_atomic(path, buf.getvalue())
    return Path(path)


def write_keypoints_csv(
    path: str | Path, keypoints, local_to_file: np.ndarray, matched_with: np.ndarray, *, unit_scale: float = 1.0
) -> Path:
    """Canopy keypoints in file coordinates (file units): id, x, y, z (on the DEM), peak_z,
    cluster_size, matched_with (-1: unmatched)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(KEYPOINT_COLUMNS)
    xyz = apply(local_to_file, keypoints.xyz) / unit_scale
    peak = (keypoints.peak_z + local_to_file[2, 3]) / unit_scale
    for i, (p, z, n, m) in enumerate(zip(xyz, peak, keypoints.cluster_sizes, matched_with)):
        w.writerow([i, f"{p[0]:.3f}", f"{p[1]:.3f}", f"{p[2]:.3f}", f"{z:.3f}", int(n), int(m)])
    write_text_atomic(path, buf.getvalue())
    return Path(path)


def pair_vop_tables(result, reference, moving):
    """The VOP tables of a pair result: ``[(scan, to_file, vops, matched_with, file name), ...]``
    (empty when no attempt was chosen). ``to_file`` maps each scan's levelled frame (metres) into
    its file coordinates (metres)."""
    det = result.details
    if det is None or det.chosen is None:
        return []
    att = det.chosen
    ref_match = np.full(len(att.reference_vops), -1)
    mov_match = np.full(len(att.moving_vops), -1)
    if att.match is not None and len(att.match.matched_pairs):
        ref_match[att.match.matched_pairs[:, 0]] = att.match.matched_pairs[:, 1]
        mov_match[att.match.matched_pairs[:, 1]] = att.match.matched_pairs[:, 0]
    tables = []
    for scan, prep, vops, matched, name in (
        (reference, det.reference, att.reference_vops, ref_match, "reference_vops.csv"),
        (moving, det.moving, att.moving_vops, mov_match, "moving_vops.csv"),
    ):
        to_file = scan.local_to_file_matrix() @ np.linalg.inv(prep.local_to_lsf)
        tables.append((scan, to_file, vops, matched, name))
    return tables


#: The DBH columns a table of trees may give (normalised names), metres per unit of each.
DBH_COLUMNS = {"dbh_m": 1.0, "dbh_cm": 0.01, "dbh_mm": 0.001}


@dataclass(frozen=True)
class TreesTable:
    """A table of trees as read: ``columns`` as written in the file, ``rows`` as dicts keyed by
    the normalised names (:func:`~forestreg.engine.io.sniff.column_key`: lower case) with
    ``dbh_m`` in metres whatever DBH column the file gave, ``lines`` the file's line number of
    each row, ``dbh_column`` the DBH column the file gave (``dbh_m``, ``dbh_cm`` or ``dbh_mm``),
    ``notes`` what was done on reading (a DBH column converted)."""

    path: Path
    columns: tuple[str, ...]
    rows: tuple[dict[str, str], ...]
    lines: tuple[int, ...]
    dbh_column: str = "dbh_m"
    notes: tuple[str, ...] = ()


def read_trees_table(path: str | Path) -> TreesTable:
    """A table of trees: a header line (any case; ``,`` ``;`` or tab between the fields; a
    byte-order mark, blank lines and ``#`` comments allowed), then one row per tree. It needs
    ``x``, ``y`` and a DBH: ``dbh_m``, or ``dbh_cm`` / ``dbh_mm`` converted to metres (said in
    ``notes``). Values stay text; the caller checks them.

    Raises :class:`ScanReadError` naming the columns the table has and those it needs, or the line
    whose field count differs from the header's.
    """
    from .base import read_text_lines

    p, numbered = read_text_lines(path, ScanReadError, "trees table")
    if not numbered:
        raise ScanReadError(
            f"{p}: the table is empty: it needs a header with x, y and dbh_m (or dbh_cm, dbh_mm), then one row per tree"
        )
    delimiter = table_delimiter(numbered[0][1])
    try:
        parsed = list(csv.reader(io.StringIO("\n".join(line for _, line in numbered)), delimiter=delimiter))
    except csv.Error as exc:
        raise ScanReadError(f"{p}: cannot be read as a table: {exc}") from exc
    columns = [c.strip() for c in parsed[0]]
    keys = [column_key(c) for c in columns]
    dbh = [k for k in DBH_COLUMNS if k in keys]
    missing = [k for k in ("x", "y") if k not in keys] + ([] if dbh else ["dbh_m"])
    if missing:
        has = ", ".join(c for c in columns if c) or "none"
        raise ScanReadError(
            f"{p}: the table has columns {has}; it needs x, y and dbh_m (or dbh_cm, dbh_mm)"
            f" (missing: {', '.join(missing)}; delimiter {'tab' if delimiter == chr(9) else repr(delimiter)})"
        )
    twice = sorted({k for k in keys if k and keys.count(k) > 1})
    if twice:
        raise ScanReadError(f"{p}: column(s) {', '.join(twice)} given twice (names compared in any case)")
    rows, lines = [], []
    for (number, _), fields in zip(numbered[1:], parsed[1:]):
        if len(fields) != len(keys):
            raise ScanReadError(f"{p}: line {number} has {len(fields)} fields, the header {len(keys)}")
        rows.append(dict(zip(keys, (f.strip() for f in fields))))
        lines.append(number)
    notes = []
    unit = dbh[0]
    if unit != "dbh_m":
        factor = DBH_COLUMNS[unit]
        for r in rows:
            r["dbh_m"] = _scaled(r[unit], factor)
        notes.append(f"{unit} converted to metres (divided by {round(1 / factor)})")
    return TreesTable(p, tuple(columns), tuple(rows), tuple(lines), unit, tuple(notes))


def _scaled(text: str, factor: float) -> str:
    """A number written in a unit, in metres (``factor`` metres per unit); other text unchanged
    (the caller refuses it with its column and line)."""
    try:
        value = float(text)
    except ValueError:
        return text
    return repr(value * factor)
