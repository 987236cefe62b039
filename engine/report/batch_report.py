"""The HTML overview of a batch of plots (``forestreg batch``): one row per plot, failures first.

Uses the report style and helpers of the evaluation report (one self-contained file, written
atomically). Each row links to the plot's own ``report.html`` when it has one.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence
from urllib.parse import quote

from ..core.atomic import write_text_atomic
from .evaluation_report import esc, generated_line, html_page

_STATUS_COLOUR = {"ok": "#1a7f37", "failed": "#b35900", "error": "#c62828"}
_ORDER = {"error": 0, "failed": 1, "ok": 2}
#: The files of a plot's folder the batch overview links to (the batch lists those present).
LINKED_OUTPUTS = ("report.html", "poses.json", "result.json", "trees.csv")


def batch_report_html(rows: Sequence[Mapping[str, Any]], out_dir: Path, *, title: str, facts: Mapping[str, Any]) -> str:
    """The overview page of ``rows`` (the rows of ``summary.csv``) for the batch in ``out_dir``."""
    counts: dict[str, int] = {}
    for r in rows:
        counts[str(r["status"])] = counts.get(str(r["status"]), 0) + 1
    body = [f"<h1>{esc(title)}</h1>", f'<p class="small">{esc(generated_line())}</p>']
    body.append(
        "<p>"
        + ", ".join(f"<b>{n}</b> {esc(s)}" for s, n in sorted(counts.items(), key=lambda kv: _ORDER.get(kv[0], 3)))
        + f" of {len(rows)} plots. "
        + "; ".join(f"{esc(k)}: {esc(v)}" for k, v in facts.items())
        + "</p>"
    )
    with_trees = any(str(r.get("trees") or "") for r in rows)
    head = (
        ["plot", "status", "scans", "registered"]
        + (["trees"] if with_trees else [])
        + ["seconds", "peak MB", "attempts", "reason", "outputs"]
    )
    body.append("<table><thead><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr></thead><tbody>")
    for r in sorted(rows, key=lambda r: (_ORDER.get(str(r["status"]), 3), str(r["plot"]))):
        folder = out_dir / str(r["plot"])
        known = r.get("outputs")  # the plot's files, listed when it finished: no look-up per row and rewrite
        names = (
            [n for n in LINKED_OUTPUTS if n in known]
            if isinstance(known, (list, tuple))
            else [n for n in LINKED_OUTPUTS if (folder / n).is_file()]
        )
        href = quote(str(r["plot"])) + "/"  # the plot's folder in out_dir
        links = [f'<a href="{esc(href + name)}">{esc(name)}</a>' for name in names]
        colour = _STATUS_COLOUR.get(str(r["status"]), "#555")
        seconds = r.get("seconds")
        cells = [
            esc(r["plot"]),
            f'<b style="color:{colour}">{esc(r["status"])}</b>',
            esc(r.get("scans", "")),
            esc(r.get("registered", "")),
            *([esc(r.get("trees", ""))] if with_trees else []),
            esc(f"{float(seconds):.1f}" if seconds not in (None, "") else ""),
            esc(f"{float(peak):.0f}" if (peak := r.get("peak_mb")) not in (None, "") else ""),
            esc(
                str(r.get("attempts") or "")
                + (f" (retried after: {r['retried_after']})" if r.get("retried_after") else "")
            ),
            esc(r.get("reason", "")),
            " ".join(links),
        ]
        body.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    body.append("</tbody></table>")
    return html_page(title, body)


def write_batch_report(
    rows: Sequence[Mapping[str, Any]],
    out_dir: str | os.PathLike[str],
    *,
    title: str = "forestreg batch",
    facts: Mapping[str, Any] = {},
) -> Path:
    """Write ``OUT/index.html`` for the batch; returns its path."""
    out = Path(out_dir)
    path = out / "index.html"
    write_text_atomic(path, batch_report_html(rows, out, title=title, facts=facts))
    return path
