"""The output folder of ``forestreg change``: ``result.json`` and ``tree_changes.csv``.

* :func:`write_change_files` writes both (atomically, each) into a folder (the caller's
  transaction: :func:`~forestreg.engine.core.atomic.output_folder`);
* :func:`read_change_dir` reads a folder back for the desktop, scripts and tests.

``tree_changes.csv``: one row per tree; ``status`` (persisting, removed, new, outside), ``x``,
``y`` (BEFORE file coordinates, the files' unit), DBH and height in each survey and their changes
(metres), ``flag``, then the trees' ids in each survey, the 1-sigma of every value and the match
distance. Empty cells: not known or withheld.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence, Union

from ..core.atomic import write_text_atomic
from ..core.errors import ScanReadError
from ..core.jsonable import to_jsonable

__all__ = ["ChangeOutput", "read_change_dir", "write_change_files", "RESULT_FILE", "TABLE_FILE"]

PathLike = Union[str, os.PathLike[str]]
RESULT_FILE = "result.json"
TABLE_FILE = "tree_changes.csv"
TEXT_COLUMNS = ("status", "flag", "tree_id_before", "tree_id_after")


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float) or hasattr(v, "dtype"):
        f = float(v)
        return "" if not math.isfinite(f) else f"{f:.4f}"
    return str(v)


def write_change_files(
    folder: PathLike, summary: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], columns: Sequence[str]
) -> dict[str, Path]:
    """Write ``result.json`` (``summary``, JSON-able; NaN as null) and ``tree_changes.csv``
    (``rows`` in ``columns`` order; floats with 4 decimals, NaN/None empty) into ``folder``."""
    out = Path(folder)
    write_text_atomic(out / RESULT_FILE, json.dumps(to_jsonable(dict(summary), nan_as_null=True), indent=1) + "\n")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in columns])
    write_text_atomic(out / TABLE_FILE, buf.getvalue())
    return {"result": out / RESULT_FILE, "table": out / TABLE_FILE}


@dataclass(frozen=True)
class ChangeOutput:
    """A ``forestreg change`` folder read back: ``result`` (the JSON), ``rows`` (the trees; numbers
    as floats, NaN where empty; the text columns as text) and the ``folder``."""

    folder: Path
    result: dict[str, Any]
    rows: list[dict[str, Any]]

    @property
    def ok(self) -> bool:
        return self.result.get("status") == "ok"

    def by_status(self, status: str) -> list[dict[str, Any]]:
        return [r for r in self.rows if r.get("status") == status]


def read_change_dir(folder: PathLike) -> ChangeOutput:
    """Read a ``forestreg change`` output folder; :class:`ScanReadError` when it is not one."""
    f = Path(folder)
    try:
        result = json.loads((f / RESULT_FILE).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ScanReadError(f"{f} is not a change folder: cannot read {RESULT_FILE}: {exc}") from exc
    rows: list[dict[str, Any]] = []
    table = f / TABLE_FILE
    if table.exists():
        try:
            with open(table, newline="", encoding="utf-8") as fh:
                for r in csv.DictReader(fh):
                    row: dict[str, Any] = {}
                    for k, v in r.items():
                        if k in TEXT_COLUMNS:
                            row[k] = v or ""
                        else:
                            try:
                                row[k] = float(v) if v not in (None, "") else math.nan
                            except ValueError:
                                row[k] = v
                    rows.append(row)
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            raise ScanReadError(f"cannot read {table}: {exc}") from exc
    return ChangeOutput(f, result, rows)
