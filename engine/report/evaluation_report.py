"""HTML report of estimated tree parameters against field records (paper table 3, figs. 16-17).

:func:`write_evaluation_report` writes one self-contained HTML file (figures embedded as base64
PNG, matplotlib Agg): tree detection per run, the paper's table 3 with the runs side by side
(R2, RMSE, rRMSE, plus bias and n), and per parameter a scatter plot of estimate against field
value with the 1:1 line, one colour per run. :func:`scatter_png` draws one such plot.
Units: metres, m², m³, except DBH, shown in centimetres as foresters read it (files keep metres).

The small HTML helpers (:func:`html_page`, :func:`png_bytes`, :func:`img_tag`) are shared with
the trees report.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import math
import os
from typing import TYPE_CHECKING, Any, Mapping, Optional, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..core.atomic import write_text_atomic  # noqa: E402
from ..trees.evaluate import PARAMETERS  # noqa: E402
from .style import REPORT_CSS  # noqa: E402

if TYPE_CHECKING:  # pragma: no cover
    from ..trees.evaluate import Evaluation

#: One colour per run, in order (the first two: the plot report's reference and moving colours).
RUN_COLOURS = ("#1f77b4", "#d95f02", "#2ca02c", "#7b3fb5", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
RUN_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
DASH = "\u2013"

CSS = (
    REPORT_CSS
    + """
td.best { font-weight: 700; }
tr.flagged td { background: #fff3f2; }
figure { display: inline-block; vertical-align: top; }
"""
)


# ------------------------------------------------------------------------------------------------
# shared HTML helpers
# ------------------------------------------------------------------------------------------------


def esc(text: Any) -> str:
    """HTML-escaped text."""
    return html.escape(str(text), quote=True)


def png_bytes(fig: Any, dpi: int = 100) -> bytes:
    """A matplotlib figure as PNG bytes (the figure is closed)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()


def img_tag(png: bytes, alt: str, ident: str) -> str:
    """An ``<img>`` with the PNG embedded (base64)."""
    data = base64.b64encode(png).decode("ascii")
    return f'<img id="{esc(ident)}" alt="{esc(alt)}" src="data:image/png;base64,{data}">'


def html_page(title: str, body: Sequence[str]) -> str:
    """A complete HTML document with the report style."""
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{esc(title)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n"
        + "\n".join(body)
        + "\n</body>\n</html>\n"
    )


def generated_line() -> str:
    """ "generated <date> by forestreg <version>"."""
    try:
        from ..._version import __version__ as version
    except Exception:  # pragma: no cover - defensive
        version = "?"
    return f"generated {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} by forestreg {version}"


def fmt(value: Any, digits: int, scale: float = 1.0) -> str:
    """A number for a table cell (a dash where missing)."""
    if value is None or isinstance(value, bool):
        return DASH
    try:
        v = float(value)
    except (TypeError, ValueError):
        return DASH
    if not math.isfinite(v):
        return DASH
    return f"{v * scale:.{digits}f}"


# ------------------------------------------------------------------------------------------------
# display units
# ------------------------------------------------------------------------------------------------


def display_unit(parameter: str) -> tuple[float, str, int]:
    """(scale, unit, decimals) a parameter is shown with: DBH in cm, the rest in its own unit."""
    if parameter == "dbh_m":
        return 100.0, "cm", 2
    unit = PARAMETERS[parameter].unit
    return 1.0, unit, 3 if parameter == "volume_m3" else 2


def run_colour(k: int) -> str:
    return RUN_COLOURS[k % len(RUN_COLOURS)]


# ------------------------------------------------------------------------------------------------
# figures
# ------------------------------------------------------------------------------------------------


def scatter_png(runs: Mapping[str, "Evaluation"], parameter: str, *, dpi: int = 100) -> Optional[bytes]:
    """Estimate against field value of one parameter, one colour per run, with the 1:1 line and
    each run's n, R2 and RMSE in the legend; None when no run has a pair for it."""
    series = [
        (name, ev.stats[parameter]) for name, ev in runs.items() if parameter in ev.stats and ev.stats[parameter].n > 0
    ]
    if not series:
        return None
    info = PARAMETERS[parameter]
    scale, unit, digits = display_unit(parameter)
    fig, ax = plt.subplots(figsize=(5.4, 5.2))
    lo, hi = math.inf, -math.inf
    for k, (name, s) in enumerate(series):
        e, f = s.estimate * scale, s.field_value * scale
        lo, hi = min(lo, e.min(), f.min()), max(hi, e.max(), f.max())
        label = f"{name}: n={s.n}, R²={s.r2_text()}, RMSE={fmt(s.rmse, digits, scale)} {unit}"
        ax.scatter(
            f,
            e,
            s=26,
            c=run_colour(k),
            marker=RUN_MARKERS[k % len(RUN_MARKERS)],
            alpha=0.8,
            edgecolors="white",
            linewidths=0.4,
            label=label,
            zorder=3,
        )
    pad = 0.05 * (hi - lo) if hi > lo else max(abs(hi), 1.0) * 0.1
    lo, hi = lo - pad, hi + pad
    ax.plot([lo, hi], [lo, hi], ls="--", c="0.35", lw=1.0, label="1:1", zorder=2)
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_aspect("equal")
    ax.set_xlabel(f"field {info.label} ({unit})")
    ax.set_ylabel(f"estimated {info.label} ({unit})")
    ax.set_title(f"{info.label}: {info.description}", fontsize=10)
    ax.grid(True, lw=0.3)
    ax.legend(loc="upper left", fontsize=7.5, framealpha=0.9)
    fig.tight_layout()
    return png_bytes(fig, dpi)


# ------------------------------------------------------------------------------------------------
# report
# ------------------------------------------------------------------------------------------------


def write_evaluation_report(
    path: str | os.PathLike[str],
    runs: Mapping[str, "Evaluation"],
    *,
    title: Optional[str] = None,
    figures: Optional[Mapping[str, bytes]] = None,
) -> None:
    """Write the evaluation report of ``runs`` (name -> evaluation) to ``path`` (atomically).

    ``figures``: scatter PNGs per parameter already drawn (by :func:`scatter_png`); missing ones
    are drawn here.
    """
    write_text_atomic(path, evaluation_report_html(runs, title=title, figures=figures))


def evaluation_report_html(
    runs: Mapping[str, "Evaluation"],
    *,
    title: Optional[str] = None,
    figures: Optional[Mapping[str, bytes]] = None,
) -> str:
    """The report of :func:`write_evaluation_report` as an HTML string."""
    title = title or "forestreg: tree parameters against field data"
    names = list(runs)
    params = [p for p in PARAMETERS if any(p in ev.stats for ev in runs.values())]
    swatches = " ".join(
        f'<span class="swatch" style="background:{run_colour(k)}"></span>{esc(n)}' for k, n in enumerate(names)
    )
    body = [
        f"<h1>{esc(title)}</h1>",
        f'<p class="sub">{len(names)} run(s): {swatches} &middot; {esc(generated_line())}</p>',
        _detection_section(runs),
        _table3_section(runs, params),
    ]
    figs = dict(figures or {})
    imgs = []
    for p in params:
        png = figs.get(p) or scatter_png(runs, p)
        if png is not None:
            imgs.append(
                f"<figure>{img_tag(png, f'{PARAMETERS[p].label} estimate against field', f'scatter_{p}')}</figure>"
            )
    body.append("<h2>3. Estimates against field values</h2>")
    body.append("".join(imgs) if imgs else "<p>No parameter has a matched pair with both values.</p>")
    body.append(
        '<p class="note">Each point is a matched tree: its field value (x) and the estimate (y); on the dashed 1:1 line '
        "they agree. One colour per run (as in the paper's figures 16-17).</p>"
    )
    body.append(_notes_section(runs))
    return html_page(title, body)


def _detection_section(runs: Mapping[str, "Evaluation"]) -> str:
    rows = []
    for k, (name, ev) in enumerate(runs.items()):
        d, m = ev.detection, ev.match
        how = f"by position, within {m.max_distance_m:g} m" if m.by == "position" else "by tree id"
        mean_d = float(np.nanmean(m.distance_m)) if len(m) and np.isfinite(m.distance_m).any() else None
        rows.append(
            f'<tr><td><span class="swatch" style="background:{run_colour(k)}"></span>{esc(name)}</td>'
            f'<td class="num">{d.field_trees}</td><td class="num">{d.estimated_trees}</td><td class="num">{d.matched}</td>'
            f'<td class="num">{d.omitted} ({fmt(d.omission_rate, 1, 100.0)} %)</td>'
            f'<td class="num">{d.commission} ({fmt(d.commission_rate, 1, 100.0)} %)</td>'
            f'<td class="num">{fmt(mean_d, 2)}</td><td>{esc(how)}</td></tr>'
        )
    return (
        "<h2>1. Tree detection</h2>"
        "<table><tr><th>Run</th><th>Field trees</th><th>Estimated trees</th><th>Matched</th>"
        "<th>Omitted field trees</th><th>Commission</th><th>Mean stem distance (m)</th><th>Matching</th></tr>"
        + "".join(rows)
        + "</table>"
        '<p class="note">Omitted: field trees with no estimated tree (rate: of the field trees). Commission: estimated '
        "trees with no field tree (rate: of the estimated trees). Matching by position pairs each estimated tree with at "
        "most one field tree, the most pairs within the distance gate and, among those, the least total distance.</p>"
    )


def _table3_section(runs: Mapping[str, "Evaluation"], params: Sequence[str]) -> str:
    names = list(runs)
    groups = (
        ("r2", "R²", lambda v: -v),
        ("rmse", "RMSE", lambda v: v),
        ("rrmse_percent", "rRMSE (%)", lambda v: v),
        ("bias", "Bias", lambda v: abs(v)),
        ("n", "n", None),
    )
    head1 = (
        '<tr><th rowspan="2">Parameter</th>'
        + "".join(f'<th colspan="{len(names)}">{label}</th>' for _, label, _ in groups)
        + "</tr>"
    )
    head2 = "<tr>" + "".join(f"<th>{esc(n)}</th>" for _ in groups for n in names) + "</tr>"
    rows = []
    for p in params:
        info = PARAMETERS[p]
        scale, unit, digits = display_unit(p)
        cells = [f'<td><b>{esc(info.label)}</b> <span class="note">({esc(unit)})</span></td>']
        for metric, _, key in groups:
            values = []
            for n in names:
                s = runs[n].stats.get(p)
                values.append(None if s is None else (s.n if metric == "n" else getattr(s, metric)))
            finite = [v for v in values if v is not None and math.isfinite(float(v))]
            best = None
            if key is not None and len(names) > 1 and len(finite) > 1:
                best = min(finite, key=key)
            for n, v in zip(names, values):
                s = runs[n].stats.get(p)
                tip = ""
                if metric == "n":
                    text = DASH if v is None else str(int(v))
                elif metric in ("rmse", "bias"):
                    text = fmt(v, digits, scale)
                elif metric == "r2" and s is not None and v is not None and not math.isfinite(float(v)):
                    text, tip = "n/a", s.r2_note or "undefined"
                else:
                    text = fmt(v, 2)
                cls = "num best" if best is not None and v is not None and v == best else "num"
                title = f' title="R² undefined: {esc(tip)}"' if tip else ""
                cells.append(f'<td class="{cls}"{title}>{esc(text)}</td>')
        rows.append("<tr>" + "".join(cells) + "</tr>")
    table = "<table>" + head1 + head2 + "".join(rows) + "</table>" if rows else "<p>No parameter to compare.</p>"
    undefined = sorted(
        {
            f"{PARAMETERS[p].label} ({esc(n)}): {esc(runs[n].stats[p].r2_note)}"
            for p in params
            for n in names
            if p in runs[n].stats and runs[n].stats[p].n > 0 and runs[n].stats[p].r2_note
        }
    )
    if undefined:
        table += (
            '<p class="note">R² n/a: undefined where the field values do not spread (SS<sub>tot</sub> = 0) or there are '
            "fewer than 2 pairs: " + "; ".join(undefined) + ".</p>"
        )
    return (
        "<h2>2. Evaluation of the estimated parameters (paper table 3)</h2>"
        + table
        + '<p class="note">RMSE and bias in the unit given after the parameter (DBH in cm); the better run of each figure '
        "is in bold (highest R², lowest RMSE and rRMSE, smallest absolute bias). n: matched trees with both values.</p>"
    )


def _notes_section(runs: Mapping[str, "Evaluation"]) -> str:
    seen: dict[tuple[str, str, str], list[str]] = {}
    for name, ev in runs.items():
        for what, table in (("estimates", ev.estimated), ("field data", ev.field_table)):
            for note in table.notes:
                seen.setdefault((what, table.source, note), []).append(name)
    notes = [
        f"<li>{esc(what)} ({esc(source)}; run {esc(', '.join(names))}): {esc(note)}</li>"
        for (what, source, note), names in seen.items()
    ]
    out = [
        "<h2>Definitions</h2>",
        "<ul>"
        "<li><b>R²</b> = 1 &minus; SS<sub>res</sub> / SS<sub>tot</sub>, the coefficient of determination of the estimates "
        "as predictions of the field values: SS<sub>res</sub> = &Sigma;(estimate &minus; field)², SS<sub>tot</sub> = "
        "&Sigma;(field &minus; mean field)². It is not the squared correlation of a fitted line: a systematic bias lowers it, "
        "and it is negative when the estimates are worse than the field mean.</li>"
        "<li><b>RMSE</b> = &radic;(mean (estimate &minus; field)²); <b>rRMSE</b> = 100 &middot; RMSE / mean field value; "
        "<b>bias</b> = mean (estimate &minus; field).</li>"
        "</ul>",
    ]
    if notes:
        out.append("<p>On reading the tables:</p><ul>" + "".join(notes) + "</ul>")
    return "\n".join(out)


__all__ = [
    "scatter_png",
    "write_evaluation_report",
    "evaluation_report_html",
    "display_unit",
    "html_page",
    "png_bytes",
    "img_tag",
    "esc",
    "fmt",
    "generated_line",
    "RUN_COLOURS",
]
