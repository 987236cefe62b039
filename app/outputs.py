"""The output folder of a registration-like run (a pair, a co-registration), written as one
transaction: the run's own files, its figure or report (a failure to draw it is logged, never
loses the result), ``transform.txt`` when the run is "ok" (the ``result.json`` matrix, the files'
unit) and ``result.json`` (the summary, indented by 2, ending with a newline)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Callable, Optional

import numpy as np

__all__ = ["write_result_folder"]

log = logging.getLogger("forestreg")


def write_result_folder(
    out: Path,
    command: str,
    summary: dict,
    write_files: Callable[[Path], None],
    *,
    draw: Optional[Callable[[Path], None]] = None,
    drawn_name: str = "",
) -> Optional[Path]:
    """Write the folder ``out`` of ``command`` (``"register"``, ``"coregister"``; see
    :func:`~forestreg.engine.core.atomic.output_folder`) as one transaction.

    ``write_files(tmp)`` writes the run's own files into the folder being made; ``draw(tmp)``
    (optional) its figure or report, ``drawn_name`` in that folder, whose failure is logged as a
    warning and leaves the rest; ``transform.txt`` is written when ``summary["status"]`` is "ok",
    then ``result.json``. Returns the path the drawing has in ``out`` (None: none drawn)."""
    from ..engine.core.atomic import output_folder, write_text_atomic
    from ..engine.core.transform import format_matrix

    drawn = False
    with output_folder(out, command) as tmp:
        write_files(tmp)
        if draw is not None:
            try:
                draw(tmp)
                drawn = (tmp / drawn_name).exists()
            except Exception as exc:  # a figure must never lose the result
                log.warning("could not draw the figure: %s", exc)
        if summary["status"] == "ok":
            write_text_atomic(tmp / "transform.txt", format_matrix(np.asarray(summary["matrix"])))
        write_text_atomic(tmp / "result.json", json.dumps(summary, indent=2) + "\n")
    return out / drawn_name if drawn else None
