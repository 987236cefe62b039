"""Writing a simulated plot or re-survey (:mod:`forestreg.engine.simulate`, which computes the
clouds and their truth in memory and writes no file) into a folder.

* :func:`write_simulated_plot`: ``scan_01.laz``, ``scan_02.laz``, ... (each scan in its scanner's
  own frame, :func:`~forestreg.engine.io.write_scan`) and ``truth.json`` (the plot's truth, each
  scan's entry naming its file);
* :func:`write_resurvey`: ``before.laz``, ``after.laz`` (each survey merged, in its own frame) and
  ``truth.json``.

The writers take the simulator's records by their attributes (this module imports no domain
package) and return them with the files written.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Optional, Union

from ..core.atomic import write_text_atomic
from ..core.progress import ProgressCallback

__all__ = ["write_resurvey", "write_simulated_plot"]

PathLike = Union[str, os.PathLike[str]]


def write_simulated_plot(plot: Any, out_dir: PathLike, *, progress: Optional[ProgressCallback] = None) -> Any:
    """Write a :class:`~forestreg.engine.simulate.plot.SimulatedPlot` into ``out_dir`` (created if
    missing): ``<scan name>.laz`` per scan, in order, then ``truth.json`` (``indent=1``) whose scan
    entries name their files (``"file"``). Returns the plot with ``out_dir``, ``files`` and that
    truth."""
    from . import write_scan

    report = progress or (lambda fraction, message: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    entries = [dict(e) for e in plot.truth.get("scans", [])]
    files = []
    for k, sim in enumerate(plot.scans):
        path = out / f"{sim.scan.name}.laz"
        report(0.95 * k / max(len(plot.scans), 1), f"writing {path.name}")
        write_scan(sim.scan, path)
        files.append(path)
        if k < len(entries):
            entries[k]["file"] = path.name
    truth = {**plot.truth, "scans": entries}
    report(0.97, "writing truth.json")
    write_text_atomic(out / "truth.json", json.dumps(truth, indent=1))
    report(1.0, "done")
    return dataclasses.replace(plot, truth=truth, out_dir=out, files=tuple(files))


def write_resurvey(case: Any, out_dir: PathLike) -> Any:
    """Write a :class:`~forestreg.engine.simulate.resurvey.ResurveyCase` into ``out_dir`` (created
    if missing): ``before.laz`` (scene frame), ``after.laz`` (the later survey's frame) and
    ``truth.json``. Returns the case with ``files`` ("before", "after", "truth" -> path)."""
    from ..core.scan import Scan
    from . import write_scan

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {"before": out / "before.laz", "after": out / "after.laz", "truth": out / "truth.json"}
    write_scan(Scan.from_points(case.before, name="before"), files["before"])
    write_scan(Scan.from_points(case.after, name="after"), files["after"])
    write_text_atomic(files["truth"], json.dumps(case.truth, indent=1))
    return dataclasses.replace(case, files=files)
