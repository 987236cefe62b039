"""The report of ``forestreg change``: a change map and the figures of the comparison, one HTML file.

:func:`change_map_png` draws the map with Pillow (:mod:`.topview`): the BEFORE stem band in grey,
persisting trees as circles coloured by their DBH growth, removed trees as red crosses, new trees
as blue plus signs, trees outside the other survey in grey. :func:`write_change_report` writes
``report.html`` (the map embedded) with the registration's evidence and uncertainty, the counts,
the growth figures and the table of flagged trees.

Frame: BEFORE, in its local frame (metres) for the map; the table shows the file coordinates.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import math
import os
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from ..core.atomic import write_text_atomic
from .style import REPORT_CSS
from .topview import Canvas, Panel

__all__ = ["change_map_png", "change_report_html", "write_change_report", "GROWTH_COLOURS"]

#: DBH growth classes (upper bound in mm, colour, label): shrinking, little, moderate, strong.
GROWTH_COLOURS = (
    (0.0, "#7f7f7f", "DBH growth < 0 or not measured"),
    (10.0, "#a1d99b", "growth 0-10 mm"),
    (25.0, "#41ab5d", "growth 10-25 mm"),
    (math.inf, "#005a32", "growth > 25 mm"),
)
REMOVED_COLOUR = "#d62728"
NEW_COLOUR = "#1f77b4"


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


def growth_colour(dbh_change_m: float) -> str:
    """The map colour of a persisting tree's DBH growth (metres; NaN: not measured)."""
    if not math.isfinite(dbh_change_m) or dbh_change_m < 0:
        return GROWTH_COLOURS[0][1]
    mm = 1000.0 * dbh_change_m
    return next(c for hi, c, _ in GROWTH_COLOURS[1:] if mm < hi)


def change_map_png(
    rows: Sequence[Mapping[str, Any]],
    background_xy: Optional[np.ndarray] = None,
    *,
    dpi: int = 100,
    title: str = "change map",
) -> bytes:
    """The change map as PNG bytes. ``rows``: trees with ``status``, ``x``, ``y`` (metres, the
    map's frame), ``dbh_before_m``/``dbh_after_m``/``dbh_change_m``; ``background_xy`` (N, 2)
    points drawn in grey beneath (e.g. the BEFORE stem band), same frame."""
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows]).reshape(-1, 2)
    bg = np.zeros((0, 2)) if background_xy is None else np.asarray(background_xy, dtype=float).reshape(-1, 2)
    if len(bg) > 150000:
        bg = bg[np.random.default_rng(0).choice(len(bg), 150000, replace=False)]
    every = np.vstack([xy, bg]) if len(bg) else xy
    if len(every) == 0:
        every = np.zeros((1, 2))
    lo, hi = every.min(axis=0), every.max(axis=0)
    canvas = Canvas(9.0, 9.0, dpi)
    panel = Panel(canvas, (0.1, 0.06, 0.97, 0.92), lo, hi)
    if len(bg):
        panel.points(bg, "0.8", 1.0)
    panel.frame(title)

    def size(r: Mapping[str, Any]) -> float:
        d = next((float(r.get(k)) for k in ("dbh_after_m", "dbh_before_m") if _finite(r.get(k))), 0.2)
        return float(np.clip(60.0 + 900.0 * d, 40.0, 600.0))

    for status, marker in (("outside", "o"), ("persisting", "o"), ("removed", "x"), ("new", "+")):
        subset = [r for r in rows if r.get("status") == status]
        for r in subset:
            colour = {"outside": "0.6", "removed": REMOVED_COLOUR, "new": NEW_COLOUR}.get(status) or growth_colour(
                _num(r.get("dbh_change_m"))
            )
            panel.markers(
                np.array([[float(r["x"]), float(r["y"])]]),
                marker,
                colour,
                size=size(r),
                line_pt=2.4 if status == "persisting" else 2.0,
            )
    for _, colour, label in GROWTH_COLOURS[1:] + GROWTH_COLOURS[:1]:
        panel.markers(
            np.zeros((0, 2)),
            "o",
            colour,
            size=80,
            line_pt=2.4,
            label=f"persisting, {label.replace('DBH growth', 'growth')}",
        )
    panel.markers(np.zeros((0, 2)), "x", REMOVED_COLOUR, size=80, line_pt=2.0, label="removed")
    panel.markers(np.zeros((0, 2)), "+", NEW_COLOUR, size=80, line_pt=2.0, label="new")
    if any(r.get("status") == "outside" for r in rows):
        panel.markers(np.zeros((0, 2)), "o", "0.6", size=80, line_pt=2.0, label="outside the other survey")
    panel.legend()
    buf = io.BytesIO()
    canvas.save(buf)
    return buf.getvalue()


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _finite(v: Any) -> bool:
    return math.isfinite(_num(v))


def _fmt(v: Any, digits: int, scale: float = 1.0) -> str:
    f = _num(v)
    return "\u2013" if not math.isfinite(f) else f"{f * scale:.{digits}f}"


def change_report_html(
    summary: Mapping[str, Any],
    rows: Sequence[Mapping[str, Any]],
    map_png: Optional[bytes],
    *,
    file_rows: Optional[Sequence[Mapping[str, Any]]] = None,
) -> str:
    """The report page: ``summary`` (the ``result.json``), ``rows`` (the trees), ``map_png`` (the
    change map); ``file_rows`` the rows in file coordinates for the table (default ``rows``)."""
    try:
        from ..._version import __version__ as version
    except Exception:  # pragma: no cover - defensive
        version = "?"
    body = [
        f'<h1>forestreg change</h1><p class="sub">BEFORE {_e(summary.get("before", ""))}<br>AFTER {_e(summary.get("after", ""))}<br>'
        f"generated {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} by forestreg {_e(version)}</p>"
    ]
    ev = summary.get("evidence") or {}
    unc = summary.get("uncertainty") or {}
    if summary.get("status") != "ok":
        body.append(
            f'<div class="failbox"><b>No comparison: the surveys could not be registered.</b><br>{_e(summary.get("reason", ""))}</div>'
        )
    else:
        body.append(
            '<div class="okbox"><b>AFTER registered onto BEFORE</b> from '
            f"{_e(ev.get('persisting_stems'))} persisting stems: 1-sigma {_fmt(unc.get('translation_m'), 1, 100)} cm, "
            f"{_fmt(unc.get('rotation_deg'), 3)} deg (at the plot centre).</div>"
        )
    counts = summary.get("trees") or {}
    body.append(
        "<h2>Trees</h2><table><tr><th>status</th><th>trees</th><th>meaning</th></tr>"
        + "".join(
            f'<tr><td>{s}</td><td class="num">{int(counts.get(s, 0))}</td><td>{m}</td></tr>'
            for s, m in (
                ("persisting", "a stem in both surveys (or seen but not measured in one: flagged)"),
                ("removed", "a stem in BEFORE whose place AFTER sees without a stem"),
                ("new", "a stem in AFTER whose place BEFORE saw without a stem"),
                ("outside", "the other survey did not cover the place: not compared"),
            )
        )
        + "</table>"
    )
    if map_png:
        data = base64.b64encode(map_png).decode("ascii")
        body.append(
            '<h2>Change map</h2><figure><img id="change-map" alt="change map" src="data:image/png;base64,'
            f'{data}"><figcaption>BEFORE frame (metres, local). Grey: BEFORE stems 0.3-3 m above the ground. Circles: '
            "persisting trees, coloured by DBH growth; red crosses: removed; blue plus signs: new. Marker size grows with the DBH."
            "</figcaption></figure>"
        )
    pers = [r for r in rows if r.get("status") == "persisting"]
    d = np.array([_num(r.get("dbh_change_m")) for r in pers])
    h = np.array([_num(r.get("height_change_m")) for r in pers])
    if len(pers):
        dd, hh = d[np.isfinite(d)], h[np.isfinite(h)]
        body.append(
            "<h2>Growth of the persisting trees</h2><table><tr><th></th><th>trees with a value</th><th>median</th><th>mean</th><th>range</th></tr>"
            + (
                f'<tr><td>DBH change (mm)</td><td class="num">{len(dd)}</td><td class="num">{_fmt(np.median(dd), 1, 1000)}</td>'
                f'<td class="num">{_fmt(dd.mean(), 1, 1000)}</td><td class="num">{_fmt(dd.min(), 0, 1000)} to {_fmt(dd.max(), 0, 1000)}</td></tr>'
                if len(dd)
                else ""
            )
            + (
                f'<tr><td>height change (m)</td><td class="num">{len(hh)}</td><td class="num">{_fmt(np.median(hh), 2)}</td>'
                f'<td class="num">{_fmt(hh.mean(), 2)}</td><td class="num">{_fmt(hh.min(), 1)} to {_fmt(hh.max(), 1)}</td></tr>'
                if len(hh)
                else ""
            )
            + '</table><p class="note">A change is left empty where one survey cannot support the value (stem occluded, '
            "DBH fit unsure, top unseen): see the flags below and <code>tree_changes.csv</code>.</p>"
        )
    if ev:
        keys = [
            ("stems_before", "stems in BEFORE"),
            ("stems_after", "stems in AFTER"),
            ("persisting_stems", "persisting stems used"),
            ("coarse_matched", "stems matched by the best heading"),
            ("second_matched", "...by the best distinct alternative"),
            ("coarse_heading_deg", "heading found (deg)"),
            ("stem_residual_rms_m", "stem residual after the fit, rms (m)"),
        ]
        rows_html = "".join(
            f'<tr><td>{label}</td><td class="num">{_e(ev.get(k))}</td></tr>'
            for k, label in keys
            if ev.get(k) is not None
        )
        ref = ev.get("refinement") or {}
        if ref:
            rows_html += f"<tr><td>refinement on stem slices and terrain</td><td>{'used' if ref.get('used') else _e(ref.get('why', 'not used'))}</td></tr>"
        body.append(f"<h2>Registration evidence</h2><table>{rows_html}</table>")
        if summary.get("matrix") is not None:
            m = summary["matrix"]
            body.append(
                "<p>matrix (p_before = matrix @ p_after, file coordinates):</p><pre>"
                + "\n".join(" ".join(f"{float(v):14.6f}" for v in row) for row in m)
                + "</pre>"
            )
    shown = list(file_rows if file_rows is not None else rows)
    flagged = [r for r in shown if r.get("flag")]
    if flagged:
        body.append(
            "<h2>Flagged trees</h2><table><tr><th>status</th><th>x</th><th>y</th><th>flag</th></tr>"
            + "".join(
                f'<tr><td>{_e(r.get("status"))}</td><td class="num">{_fmt(r.get("x"), 2)}</td><td class="num">{_fmt(r.get("y"), 2)}</td>'
                f"<td>{_e(r.get('flag'))}</td></tr>"
                for r in flagged
            )
            + "</table>"
        )
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>forestreg change</title>\n'
        f"<style>{REPORT_CSS}</style>\n</head>\n<body>\n" + "\n".join(body) + "\n</body>\n</html>\n"
    )


def write_change_report(
    folder: str | os.PathLike[str],
    summary: Mapping[str, Any],
    rows: Sequence[Mapping[str, Any]],
    background_xy: Optional[np.ndarray] = None,
    *,
    file_rows: Optional[Sequence[Mapping[str, Any]]] = None,
) -> str:
    """Write ``report.html`` into ``folder``; returns its path. ``rows`` in the map's frame
    (BEFORE local), ``file_rows`` the same trees in file coordinates."""
    png = change_map_png(rows, background_xy) if rows else None
    path = os.path.join(os.fspath(folder), "report.html")
    write_text_atomic(path, change_report_html(summary, rows, png, file_rows=file_rows))
    return path
