"""The HTML report of a registered plot (one self-contained file, for a forest ecologist).

:func:`write_plot_report` writes one HTML file with every figure embedded (base64 PNG, matplotlib
Agg, no external assets), written atomically:

1. summary: plot, centre scan, scans registered / failed (failures and their reasons first), the
   parameters used;
2. top view (the paper's figure 8 idea): each registered scan's slice at scanner height in its own
   colour, its visual occlusion points (VOPs), the scanners, and the VOPs of linked scans that
   coincide in the project frame (the matched trunks) ringed and joined;
3. one row per link in the layout of the paper's table 4 (``P_s`` = reference VOPs, ``P_t`` =
   moving VOPs, ``P_s n P_t`` = matched; the paper's "source" is our reference) and a bar chart of
   the ICP standard deviation per link;
4. with a global adjustment: each link's disagreement with the poses before and after it;
5. with a ``comparison`` (marker-free against manual registration): the paper's tables 4 and 5,
   the difference between the two results per pair, and bars per pair and per target.

Frames: everything is drawn in the project frame (the centre scan's file coordinates), shifted so
that the centre scanner is at (0, 0). Slice points and VOPs are computed in each scan's levelled
scanner frame (LSF) and carried LSF -> local -> file -> project with the scan's pose.
"""

from __future__ import annotations

import base64
import dataclasses
import datetime as _dt
import html
import io
import math
import os
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import to_rgb  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from ..core.atomic import write_text_atomic  # noqa: E402
from ..core.uncertainty import evidence_notes  # noqa: E402
from ..tls.params import RegistrationParams  # noqa: E402
from ..tls.plot import ScanCache  # noqa: E402
from ..tls.project import Link, Project  # noqa: E402
from .style import REPORT_CSS  # noqa: E402
from .views import (  # noqa: E402
    MATCH_COLOUR,
    MOVING_COLOUR,
    REFERENCE_COLOUR,
    ScanState,
    TopView,
    compute_top_view,
    failure_reason,
    scan_colours,
    scan_states,
)

AUTO_COLOUR = REFERENCE_COLOUR
MANUAL_COLOUR = MOVING_COLOUR
DASH = "\u2013"
ARROW = "\u2192"

# ------------------------------------------------------------------------------------------------
# public API
# ------------------------------------------------------------------------------------------------


def write_plot_report(
    project: Project,
    path: str | os.PathLike[str],
    *,
    scans: Optional[ScanCache] = None,
    comparison: Optional[Mapping[str, Any]] = None,
    title: Optional[str] = None,
) -> None:
    """Write the HTML report of a registered plot to ``path`` (atomically).

    Parameters
    ----------
    project : the plot project; its link results, poses and adjustment are reported as they are.
    path : the HTML file to write (its folder must exist).
    scans : a :class:`~forestreg.engine.tls.plot.ScanCache` of the project (reuse it to avoid reading
        the scans again); by default one is made. Slices and VOPs computed for the top view are
        kept with it, so a second report from the same cache is quick.
    comparison : optional marker-free against manual comparison (see the module docstring and
        :func:`comparison_section`): adds the paper's tables 4 and 5 and their bar charts.
    title : the report's title; default "forestreg report: <plot name>".
    """
    text = plot_report_html(project, scans=scans, comparison=comparison, title=title)
    write_text_atomic(path, text)


def plot_report_html(
    project: Project,
    *,
    scans: Optional[ScanCache] = None,
    comparison: Optional[Mapping[str, Any]] = None,
    title: Optional[str] = None,
) -> str:
    """The report of :func:`write_plot_report` as an HTML string."""
    scans = scans or ScanCache(project)
    title = title or f"forestreg report: {project.name}"
    states = scan_states(project)
    colours = scan_colours(project)
    view = compute_top_view(project, scans)
    body = [
        f"<h1>{_e(title)}</h1>",
        f'<p class="sub">Plot <b>{_e(project.name)}</b> &middot; {len(project.scans)} scans &middot; '
        f"generated {_e(_dt.datetime.now().strftime('%Y-%m-%d %H:%M'))} by forestreg {_e(_version())}</p>",
        _summary_section(project, states, colours, view),
        _top_view_section(project, view, colours),
        _links_section(project, view, colours),
    ]
    body.append(_uncertainty_section(project, states))
    if project.adjustment:
        body.append(_adjustment_section(project))
    if comparison:
        body.append(comparison_section(comparison))
    body.append(_parameters_section(project))
    body = _numbered(body)
    body.append(
        '<p class="note">Conventions: metres and degrees; a link maps the moving scan onto the reference scan '
        "(<code>p_reference = T @ p_moving</code>); the project frame is the centre scan's file coordinates. "
        "The paper's &ldquo;source&rdquo; scan is our reference (<i>P<sub>s</sub></i>), its &ldquo;target&rdquo; "
        "our moving scan (<i>P<sub>t</sub></i>).</p>"
    )
    body = _numbered_sections(body)
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{_e(title)}</title>\n<style>{REPORT_CSS}</style>\n</head>\n<body>\n"
        + "\n".join(body)
        + "\n</body>\n</html>\n"
    )


def top_view_png(project: Project, scans: Optional[ScanCache] = None, *, dpi: int = 100) -> bytes:
    """The report's top view alone, as PNG bytes (for the GUI or a quick look)."""
    scans = scans or ScanCache(project)
    view = compute_top_view(project, scans)
    return _top_view_figure(project, view, scan_colours(project), dpi=dpi)


# ------------------------------------------------------------------------------------------------
# figures
# ------------------------------------------------------------------------------------------------


def _png(fig, dpi: int, *, tight: bool = False) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, **({"bbox_inches": "tight", "pad_inches": 0.15} if tight else {}))
    plt.close(fig)
    return buf.getvalue()


def _img(png: bytes, alt: str, ident: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img id="{_e(ident)}" alt="{_e(alt)}" src="data:image/png;base64,{data}">'


def _lighter(colour: str, amount: float = 0.35) -> tuple[float, float, float]:
    r, g, b = to_rgb(colour)
    return (r + (1 - r) * amount, g + (1 - g) * amount, b + (1 - b) * amount)


def _top_view_figure(project: Project, view: TopView, colours: Mapping[str, str], *, dpi: int = 100) -> bytes:
    fig, ax = plt.subplots(figsize=(10.0, 9.5))
    o = view.origin[:2]
    handles: list[Any] = []
    drawn = sum(len(sv.slice_xy) for sv in view.scans.values())
    size = float(np.clip(60000.0 / max(drawn, 1), 0.8, 5.0))
    for name, sv in view.scans.items():
        colour = colours.get(name, "0.3")
        xy = sv.slice_xy - o
        ax.scatter(
            xy[:, 0], xy[:, 1], s=size, color=_lighter(colour, 0.2), alpha=0.6, linewidths=0, rasterized=True, zorder=1
        )
        handles.append(
            Line2D(
                [],
                [],
                ls="none",
                marker="o",
                ms=7,
                mfc="none",
                mec=colour,
                mew=1.6,
                label=f"{_short(name, 28)} ({len(sv.vops_xy)} VOPs, D_r {sv.radius_m:.0f} m)",
            )
        )
    for name, sv in view.scans.items():
        colour = colours.get(name, "0.3")
        xy = sv.vops_xy - o
        ax.scatter(xy[:, 0], xy[:, 1], s=34, facecolors="none", edgecolors=colour, linewidths=1.3, zorder=3)
        c = sv.scanner[:2] - o
        ax.add_patch(
            plt.Circle(tuple(c), sv.radius_m, fill=False, ls=(0, (4, 4)), color=colour, lw=0.7, alpha=0.6, zorder=2)
        )
    n_pairs = 0
    for lv in view.links:
        if not len(lv.pairs):
            continue
        n_pairs += len(lv.pairs)
        a = lv.pairs[:, 0] - o
        b = lv.pairs[:, 1] - o
        for p, q in zip(a, b):
            ax.plot([p[0], q[0]], [p[1], q[1]], color=MATCH_COLOUR, lw=2.0, zorder=4)
        ax.scatter(
            (a[:, 0] + b[:, 0]) / 2,
            (a[:, 1] + b[:, 1]) / 2,
            s=140,
            facecolors="none",
            edgecolors=MATCH_COLOUR,
            linewidths=1.8,
            zorder=4,
        )
    for name, sv in view.scans.items():
        colour = colours.get(name, "0.3")
        c = sv.scanner[:2] - o
        ax.plot(c[0], c[1], marker="^", ms=13, mfc=colour, mec="k", mew=1.2, ls="none", zorder=6)
        ax.annotate(
            _short(name, 24),
            xy=(c[0], c[1]),
            xytext=(9, 9),
            textcoords="offset points",
            fontsize=10,
            fontweight="bold",
            color="k",
            zorder=7,
            bbox=dict(boxstyle="round,pad=0.25", fc="white", ec=colour, lw=1.2, alpha=0.9),
        )
    handles.append(
        Line2D(
            [],
            [],
            ls="none",
            marker="o",
            ms=11,
            mfc="none",
            mec=MATCH_COLOUR,
            mew=1.8,
            label=f"VOPs matched across a link ({n_pairs})",
        )
    )
    handles.append(Line2D([], [], ls="none", marker="^", ms=10, mfc="0.6", mec="k", label="scanner"))
    handles.append(Line2D([], [], ls=(0, (4, 4)), color="0.4", lw=0.8, label="VOP radius D_r"))
    if view.scans:
        allxy = (
            np.concatenate(
                [sv.slice_xy for sv in view.scans.values()] + [sv.scanner[None, :2] for sv in view.scans.values()]
            )
            - o
        )
        lo, hi = np.percentile(allxy, 0.2, axis=0) - 2.0, np.percentile(allxy, 99.8, axis=0) + 2.0
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    else:
        ax.text(0.5, 0.5, "no registered scan to draw", ha="center", va="center", transform=ax.transAxes, fontsize=14)
    ax.set_aspect("equal")
    shifted = bool(np.any(np.abs(o) > 0.0))
    ax.set_xlabel("x (m, from the centre scanner)" if shifted else "x (m)")
    ax.set_ylabel("y (m, from the centre scanner)" if shifted else "y (m)")
    ax.grid(True, lw=0.3, color="0.8", zorder=0)
    ax.set_title(f"{_short(project.name, 40)}: slices at scanner height, trunk shadows (VOPs) and matches", fontsize=12)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)
    return _png(fig, dpi, tight=True)


@dataclass
class BarPanel:
    """One bar chart panel: a group of bars per label, one bar per series (None = "n/a")."""

    labels: Sequence[str]
    series: Sequence[tuple[str, Sequence[Optional[float]], Any]]
    ylabel: str
    title: str
    notes: Optional[Sequence[str]] = None
    digits: int = 2


def _draw_bars(ax, panel: BarPanel) -> None:
    series = panel.series
    width = 0.8 / max(len(series), 1)
    x = np.arange(len(panel.labels))
    top = max([0.0] + [float(v) for _, values, _ in series for v in values if _num(v)]) or 1.0
    for k, (name, values, colour) in enumerate(series):
        pos = x - 0.4 + width * (k + 0.5)
        vals = [float(v) if _num(v) else 0.0 for v in values]
        bars = ax.bar(
            pos, vals, width * 0.92, color=colour, label=name if len(series) > 1 else None, edgecolor="0.25", lw=0.5
        )
        for b, v in zip(bars, values):
            centre = b.get_x() + b.get_width() / 2
            if _num(v):
                ax.annotate(
                    f"{float(v):.{panel.digits}f}",
                    (centre, b.get_height()),
                    xytext=(0, 2),
                    textcoords="offset points",
                    ha="center",
                    va="bottom",
                    fontsize=8,
                )
            else:
                ax.annotate(
                    "n/a",
                    (centre, 0),
                    xytext=(0, 2),
                    textcoords="offset points",
                    ha="center",
                    va="bottom",
                    fontsize=8,
                    color="#b42318",
                )
    for xi, note in zip(x, panel.notes or ()):
        if note:
            ax.annotate(note, (xi, top * 0.5), ha="center", va="center", fontsize=9, color="#b42318", fontweight="bold")
    ax.set_xticks(x)
    slanted = len(panel.labels) > 3
    ax.set_xticklabels(
        [_short(lab, 34) for lab in panel.labels], rotation=20 if slanted else 0, ha="right" if slanted else "center"
    )
    ax.set_ylabel(panel.ylabel)
    ax.set_ylim(0, top * 1.2)
    ax.set_title(panel.title, fontsize=11)
    ax.grid(True, axis="y", lw=0.3)
    if len(series) > 1:
        ax.legend(fontsize=9)


def _bars_png(*panels: BarPanel, dpi: int = 100) -> bytes:
    """Bar chart panels side by side, as PNG bytes."""
    widths = [min(max(5.5, 0.7 * max(len(p.labels), 1) * max(len(p.series), 1) + 2.5), 14.0) for p in panels]
    fig, axes = plt.subplots(
        1, len(panels), figsize=(sum(widths), 4.3), gridspec_kw={"width_ratios": widths}, squeeze=False
    )
    for ax, panel in zip(axes[0], panels):
        _draw_bars(ax, panel)
    fig.tight_layout()
    return _png(fig, dpi)


# ------------------------------------------------------------------------------------------------
# sections


def _numbered_sections(body: list[str]) -> list[str]:
    """Number the ``<h2>N. title</h2>`` headings in the order they appear (a section left out, e.g.
    the global adjustment, leaves no gap)."""
    import re

    count = iter(range(1, 100))
    return [re.sub(r"<h2>\d+\. ", lambda m: f"<h2>{next(count)}. ", part) for part in body]


# ------------------------------------------------------------------------------------------------


def _summary_section(
    project: Project, states: Mapping[str, ScanState], colours: Mapping[str, str], view: TopView
) -> str:
    failed = [s for s in states.values() if s.status == "failed"]
    placed = [s for s in states.values() if s.status != "failed"]
    out = ["<h2>1. Summary</h2>"]
    if failed:
        items = "".join(
            f"<li><b>{_e(s.name)}</b>"
            + (f" (onto {_e(s.reference)})" if s.reference else "")
            + f": {_e(s.reason)}</li>"
            for s in failed
        )
        out.append(
            f'<div class="failbox"><h3>{len(failed)} of {len(states)} scans could not be registered</h3>'
            f'<ul>{items}</ul><p class="note">These scans are listed here and left out of the top view. '
            "Try another reference scan nearer to them, a larger D_r, or other slice heights (dh).</p></div>"
        )
    else:
        out.append(
            f'<div class="okbox">All {len(states)} scans are registered into the frame of the centre scan '
            f"<b>{_e(project.centre or DASH)}</b>.</div>"
        )
    origin = view.origin
    rows = []
    for s in project.scans:
        st = states[s.name]
        sv = view.scans.get(s.name)
        pos = (sv.scanner - origin) if sv is not None else None
        status = {
            "centre": '<span class="ok">centre (project frame)</span>',
            "registered": '<span class="ok">registered</span>',
        }.get(st.status, f'<span class="bad">failed</span>: {_e(st.reason)}')
        if s.name in view.problems:
            status += f'<br><span class="note">{_e(view.problems[s.name])}</span>'
        kind = "tilted" + (f" (beside {_e(s.level_partner)})" if s.level_partner else "") if s.tilted else "level"
        rows.append(
            f'<tr class="{"failed" if st.status == "failed" else ""}">'
            f'<td><span class="swatch" style="background:{colours.get(s.name, "#999")}"></span>{_e(s.name)}</td>'
            f"<td>{kind}</td><td>{_e(st.reference or DASH)}</td>"
            f'<td class="num">{_fmt(None if sv is None else sv.points, 0, thousands=True)}</td>'
            + "".join(f'<td class="num">{_fmt(None if pos is None else pos[i], 2)}</td>' for i in range(3))
            + f"<td>{status}</td></tr>"
        )
    adjusted = " (after the global adjustment)" if project.adjustment and project.adjustment.get("poses") else ""
    out.append(
        "<table><tr><th>Scan</th><th>Set-up</th><th>Registered onto</th><th>Points</th>"
        "<th>Scanner x (m)</th><th>Scanner y (m)</th><th>Scanner z (m)</th><th>Status</th></tr>"
        + "".join(rows)
        + "</table>"
    )
    out.append(
        f"<p>Centre scan (project frame): <b>{_e(project.centre or DASH)}</b> &middot; registered: "
        f"<b>{len(placed)}</b> of {len(states)} (centre included) &middot; failed: "
        f'<b class="{"bad" if failed else ""}">{len(failed)}</b>{_e(adjusted)}. '
        f"Scanner positions are in the project frame relative to the centre scanner"
        + (
            f" (which stands at {_e(', '.join(f'{v:.2f}' for v in origin))} m in its file coordinates)"
            if np.any(origin != 0)
            else ""
        )
        + ".</p>"
    )
    if project.path is not None:
        out.append(f'<p class="note">Project file: <code>{_e(str(project.path))}</code></p>')
    return "\n".join(out)


def _top_view_section(project: Project, view: TopView, colours: Mapping[str, str]) -> str:
    png = _top_view_figure(project, view, colours)
    total = sum(len(sv.slice_xy) for sv in view.scans.values())
    pairs = ", ".join(f"{_e(lv.moving)} {ARROW} {_e(lv.reference)}: {len(lv.pairs)}" for lv in view.links) or "none"
    return (
        "<h2>2. Top view of the registered plot</h2>"
        f"<figure>{_img(png, 'top view of the registered scans', 'topview')}"
        "<figcaption>Each registered scan's horizontal slice at scanner height (light dots, one colour per scan; "
        f"{total:,} points drawn), its visual occlusion points (VOPs, circles: where trunks begin to cast their "
        "shadows, within the dashed radius D_r of its scanner), and the scanners (triangles). Green rings join VOPs "
        f"of linked scans that coincide within D_t = {view.match_distance_m * 100:.0f} cm in the project frame: "
        f"the same trunk seen from both scanners. VOPs matched per link: {pairs}. "
        "Scans that could not be registered are not drawn.</figcaption></figure>"
    )


def _link_rows(project: Project) -> list[Link]:
    return [link for link in project.links if not link.extra] + [link for link in project.links if link.extra]


def _link_label(link: Link) -> str:
    return f"{link.moving} {ARROW} {link.reference}"


def _scanner_distance(project: Project, link: Link, view: TopView) -> Optional[float]:
    mv, rv = view.scans.get(link.moving), view.scans.get(link.reference)
    if mv is None or rv is None:
        return None
    return float(np.linalg.norm(mv.scanner - rv.scanner))


def _links_section(project: Project, view: TopView, colours: Mapping[str, str]) -> str:
    links = _link_rows(project)
    out = ["<h2>3. Registration of each link (paper table 4)</h2>"]
    if not links:
        out.append("<p>The project has no links yet: nothing was registered.</p>")
        return "\n".join(out)
    head = (
        "<tr><th>Registering scans<br>(moving " + ARROW + " reference)</th><th>Method</th>"
        "<th>Distance between scanners (m)</th><th>D<sub>r</sub> (m)</th>"
        "<th><i>P<sub>s</sub></i><br>reference VOPs</th><th><i>P<sub>t</sub></i><br>moving VOPs</th>"
        "<th><i>P<sub>s</sub></i> &cap; <i>P<sub>t</sub></i><br>matched VOPs</th>"
        "<th>Margin over next distinct solution (VOPs)</th><th>Overlap-score gap (m)</th>"
        "<th>ICP std (cm)</th><th>ICP fitness</th><th>Time (s)</th><th>Status</th></tr>"
    )
    rows = []
    labels, stds, cols, notes = [], [], [], []
    for link in links:
        r = link.result if isinstance(link.result, Mapping) else {}
        icp = r.get("icp") if isinstance(r.get("icp"), Mapping) else {}
        ok = link.ok
        matched, second = r.get("matched"), r.get("second_matched")
        margin = (matched - (second or 0)) if _num(matched) and (second is None or _num(second)) else None
        timings = r.get("timings") if isinstance(r.get("timings"), Mapping) else {}
        total_time = sum(float(v) for v in timings.values() if _num(v)) if timings else None
        method = "manual (targets + ICP)" if link.method == "manual" else "marker-free (VOPs + ICP)"
        tf = r.get("target_fit") if isinstance(r.get("target_fit"), Mapping) else None
        if tf:
            ids = tf.get("target_ids")
            method += f'<br><span class="note">{len(ids) if isinstance(ids, list) else "?"} targets, fit RMSE {_fmt(tf.get("rmse_m"), 1, 100)} cm</span>'
        if link.extra:
            method += '<br><span class="note">loop link (adjustment only)</span>'
        if len(r) == 0:  # no result yet (a failed result is a falsy record, but it was run)
            status = '<span class="bad">not run</span>'
        elif ok:
            status = '<span class="ok">ok</span>'
            after = r.get("retried_after")
            if isinstance(after, list) and after:
                status += (
                    '<br><span class="note">after failing onto '
                    + _e(
                        "; ".join(
                            f"{t.get('reference', '?')} ({t.get('reason', '')})"
                            for t in after
                            if isinstance(t, Mapping)
                        )
                    )
                    + "</span>"
                )
        else:
            status = f'<span class="bad">failed</span>: {_e(failure_reason(r))}'
        std = icp.get("std_m")
        rows.append(
            f'<tr class="{"" if ok else "failed"}">'
            f'<td><span class="swatch" style="background:{colours.get(link.moving, "#999")}"></span>{_e(_link_label(link))}</td>'
            f"<td>{method}</td>"
            f'<td class="num">{_fmt(_scanner_distance(project, link, view), 2)}</td>'
            f'<td class="num">{_fmt(r.get("vop_radius_m"), 0)}</td>'
            f'<td class="num">{_fmt(r.get("reference_vops"), 0)}</td>'
            f'<td class="num">{_fmt(r.get("moving_vops"), 0)}</td>'
            f'<td class="num"><b>{_fmt(matched, 0)}</b></td>'
            f'<td class="num">{_fmt(margin, 0)}</td>'
            f'<td class="num">{_fmt(r.get("score_gap_m"), 2)}</td>'
            f'<td class="num"><b>{format_cm(std)}</b></td>'
            f'<td class="num">{_fmt(icp.get("fitness"), 2)}</td>'
            f'<td class="num">{_fmt(total_time, 1)}</td>'
            f"<td>{status}</td></tr>"
        )
        labels.append(_link_label(link))
        stds.append(100.0 * float(std) if ok and _num(std) else None)
        cols.append(colours.get(link.moving, "0.5"))
        notes.append("" if ok else "failed")
    out.append("<table>" + head + "".join(rows) + "</table>")
    out.append(
        '<p class="note"><i>P<sub>s</sub></i>, <i>P<sub>t</sub></i>: VOPs found within D<sub>r</sub> of the reference and the '
        "moving scanner; matched: VOPs of the moving scan within D<sub>t</sub> of a reference VOP at the best horizontal "
        "solution. The margin is how many more VOPs the best solution matches than the best clearly different one, and "
        "the overlap-score gap how much better its overlap score is: the evidence that the match is not a coincidence. "
        "ICP std: standard deviation of the distances from the registered moving points to their nearest reference points "
        "(the paper's accuracy measure); fitness: the share of moving points in the shared area with a reference point "
        "within the last ICP distance. Time: the whole pair registration.</p>"
    )
    if any(v is not None for v in stds):
        png = _bars_png(
            BarPanel(
                labels,
                [("ICP std", stds, cols)],
                "ICP standard deviation (cm)",
                "ICP standard deviation per link (bar colour: moving scan)",
                notes=notes,
            )
        )
        out.append(
            f"<figure>{_img(png, 'ICP standard deviation per link', 'icpbars')}"
            "<figcaption>ICP standard deviation of each link (cm); failed links have no bar.</figcaption></figure>"
        )
    return "\n".join(out)


def _numbered(parts: list[str]) -> list[str]:
    """Number the numbered section headings 1, 2, 3 ... in the order they appear (sections are
    optional, so the numbers never jump)."""
    import re

    counter = iter(range(1, 100))
    return [re.sub(r"<h2>\d+\. ", lambda _m: f"<h2>{next(counter)}. ", part) for part in parts]


def _uncertainty_section(project: Project, states: Mapping[str, Any]) -> str:
    """Per scan: the stated 1-sigma pose uncertainty and the quality figures that need no truth;
    the links a survey dropped and why."""
    from ..tls.plot import pose_uncertainty

    adj = project.adjustment or {}
    try:
        sigma = pose_uncertainty(project)
    except Exception:  # noqa: BLE001 - a report never fails on a damaged project
        sigma = {}
    quality = adj.get("quality") if isinstance(adj.get("quality"), Mapping) else {}
    out = [
        "<h2>9. Pose uncertainty and quality</h2>",
        "<p>How far to trust each pose without ground truth: the 1-sigma uncertainty relative to the centre scan "
        "(from the trunks matched in each link, propagated along the most certain chain of links and inflated where "
        "loops disagree more than stated); the links of each scan and the largest disagreement between a link and "
        "the final poses.</p>",
    ]
    rows = []
    for s in project.scans:
        u = sigma.get(s.name) if isinstance(sigma, Mapping) else None
        q = quality.get(s.name) if isinstance(quality, Mapping) else None
        q = q if isinstance(q, Mapping) else {}
        t = u.get("translation_m") if isinstance(u, Mapping) else None
        r = u.get("rotation_deg") if isinstance(u, Mapping) else None
        rows.append(
            f'<tr><td>{_e(s.name)}</td><td class="num">{format_cm(t)}</td><td class="num">{_fmt(r, 3)}</td>'
            f'<td class="num">{_e(str(q.get("links", "-")))}</td><td class="num">{format_cm(q.get("max_residual_m"))}</td>'
            f'<td class="num">{_fmt(q.get("max_residual_deg"), 3)}</td><td class="num">{_e(str(q.get("dropped_links", "-")))}</td>'
            f'<td class="num">{format_cm(q.get("terrain_median_m"))}</td><td class="num">{_e(str(q.get("min_matched_vops", "-")))}</td>'
            f'<td class="num">{_fmt(q.get("max_ambiguity"), 2)}</td></tr>'
        )
    out.append(
        "<table><tr><th>Scan</th><th>Position 1-sigma (cm)</th><th>Rotation 1-sigma (deg)</th><th>Links</th>"
        "<th>Largest link residual (cm)</th><th>(deg)</th><th>Dropped links</th><th>Terrain disagreement (cm, median)</th>"
        "<th>Fewest matched trunks</th><th>Ambiguity (2nd / best)</th></tr>" + "".join(rows) + "</table>"
    )
    counted = []
    for link in project.links:
        notes = evidence_notes(link.result.uncertainty) if link.result is not None else []
        if notes:
            counted.append(
                f"<li>{_e(link.moving)} {ARROW} {_e(link.reference)}: {'; '.join(_e(n) for n in notes)}</li>"
            )
    if counted:
        out.append(
            "<p><b>What the links' uncertainties counted</b> (motions the surfaces hardly pin, distinct "
            "solutions that fitted nearly as well):</p><ul>" + "".join(counted) + "</ul>"
        )
    dropped = [d for d in (adj.get("dropped") or []) if isinstance(d, Mapping)]
    if dropped:
        out.append(
            "<p><b>Links dropped as inconsistent:</b></p><ul>"
            + "".join(
                f"<li>{_e(str(d.get('moving', '?')))} {ARROW} {_e(str(d.get('reference', '?')))}: {_e(str(d.get('reason', '')))}</li>"
                for d in dropped
            )
            + "</ul>"
        )
    if _num(adj.get("uncertainty_inflation")) and adj["uncertainty_inflation"] > 1.0:
        out.append(
            f'<p class="note">The loops disagree more than the links state: every stated uncertainty was multiplied by {adj["uncertainty_inflation"]:.2f}.</p>'
        )
    return "\n".join(out)


def _adjustment_section(project: Project) -> str:
    adj = project.adjustment or {}
    rows_in = [r for r in (adj.get("links") or []) if isinstance(r, Mapping)]
    out = [
        "<h2>4. Global adjustment</h2>",
        "<p>Extra links close loops; the adjustment spreads their disagreement over all links. Each row is how far the "
        "poses disagree with a link's own result, before and after the adjustment (rotation in degrees, translation "
        "at the moving scanner in cm).</p>",
    ]
    if not rows_in:
        out.append("<p>The adjustment recorded no link residuals.</p>")
        return "\n".join(out)
    rows, labels = [], []
    tb, ta, rb, ra = [], [], [], []
    for r in rows_in:
        b = r.get("before") if isinstance(r.get("before"), Mapping) else {}
        a = r.get("after") if isinstance(r.get("after"), Mapping) else {}
        label = f"{r.get('moving', '?')} {ARROW} {r.get('reference', '?')}"
        labels.append(label)
        rb.append(b.get("rotation_deg"))
        ra.append(a.get("rotation_deg"))
        tb.append(100.0 * b["translation_m"] if _num(b.get("translation_m")) else None)
        ta.append(100.0 * a["translation_m"] if _num(a.get("translation_m")) else None)
        rows.append(
            f"<tr><td>{_e(label)}</td>"
            f'<td class="num">{_fmt(b.get("rotation_deg"), 3)}</td><td class="num">{format_cm(b.get("translation_m"))}</td>'
            f'<td class="num">{_fmt(a.get("rotation_deg"), 3)}</td><td class="num">{format_cm(a.get("translation_m"))}</td></tr>'
        )
    out.append(
        '<table><tr><th rowspan="2">Link (moving ' + ARROW + ' reference)</th><th colspan="2">Before adjustment</th>'
        '<th colspan="2">After adjustment</th></tr><tr><th>Rotation (deg)</th><th>Translation (cm)</th>'
        "<th>Rotation (deg)</th><th>Translation (cm)</th></tr>" + "".join(rows) + "</table>"
    )
    png = _bars_png(
        BarPanel(
            labels,
            [("before", tb, "#9e9ac8"), ("after", ta, "#3f007d")],
            "translation residual (cm)",
            "Translation residual per link",
        ),
        BarPanel(
            labels,
            [("before", rb, "#9e9ac8"), ("after", ra, "#3f007d")],
            "rotation residual (deg)",
            "Rotation residual per link",
            digits=3,
        ),
    )
    out.append(
        f"<figure>{_img(png, 'link residuals before and after the adjustment', 'adjbars')}"
        "<figcaption>Disagreement between each link and the poses, before and after the adjustment.</figcaption></figure>"
    )
    return "\n".join(out)


def comparison_section(comparison: Mapping[str, Any]) -> str:
    """The marker-free against manual comparison (paper tables 4 and 5) as HTML.

    ``comparison`` holds ``pairs`` (each ``moving``, ``reference``, ``auto`` {status, matched,
    icp_std_m, reference_vops, moving_vops}, ``manual`` {status, icp_std_m, targets},
    ``rotation_difference_deg``, ``translation_difference_m``), ``auto_target_residual_m``,
    ``manual_target_residual_m`` and ``targets`` {"auto": {id: m}, "manual": {id: m}}; missing
    entries are shown as a dash.
    """
    pairs = [p for p in (comparison.get("pairs") or []) if isinstance(p, Mapping)]
    out = [
        "<h2>5. Marker-free against manual registration</h2>",
        "<p>The same pairs registered from trunk shadows (proposed method) and from targets picked by hand "
        "(manual method, then the same ICP), as in the paper's tables 4 and 5.</p>",
        "<h3>Per pair (paper table 4)</h3>",
    ]
    rows, labels, s_auto, s_manual, rot, trans = [], [], [], [], [], []
    for p in pairs:
        a = p.get("auto") if isinstance(p.get("auto"), Mapping) else {}
        m = p.get("manual") if isinstance(p.get("manual"), Mapping) else {}
        label = f"{p.get('moving', '?')} {ARROW} {p.get('reference', '?')}"
        labels.append(label)
        s_auto.append(100.0 * a["icp_std_m"] if _num(a.get("icp_std_m")) else None)
        s_manual.append(100.0 * m["icp_std_m"] if _num(m.get("icp_std_m")) else None)
        rot.append(p.get("rotation_difference_deg") if _num(p.get("rotation_difference_deg")) else None)
        trans.append(100.0 * p["translation_difference_m"] if _num(p.get("translation_difference_m")) else None)
        rows.append(
            f"<tr><td>{_e(label)}</td>"
            f'<td class="num">{_fmt(a.get("reference_vops"), 0)}</td><td class="num">{_fmt(a.get("moving_vops"), 0)}</td>'
            f'<td class="num">{_fmt(a.get("matched"), 0)}</td>'
            f'<td class="num"><b>{format_cm(a.get("icp_std_m"))}</b></td><td class="num"><b>{format_cm(m.get("icp_std_m"))}</b></td>'
            f'<td class="num">{_fmt(m.get("targets"), 0)}</td>'
            f'<td class="num">{_fmt(p.get("rotation_difference_deg"), 3)}</td>'
            f'<td class="num">{format_cm(p.get("translation_difference_m"))}</td>'
            f"<td>{_status_html(a.get('status'))}</td><td>{_status_html(m.get('status'))}</td></tr>"
        )
    out.append(
        '<table><tr><th rowspan="2">Registering scans<br>(moving ' + ARROW + " reference)</th>"
        '<th rowspan="2"><i>P<sub>s</sub></i></th><th rowspan="2"><i>P<sub>t</sub></i></th>'
        '<th rowspan="2"><i>P<sub>s</sub></i> &cap; <i>P<sub>t</sub></i></th>'
        '<th colspan="2">ICP standard deviation (cm)</th><th rowspan="2">Targets (manual)</th>'
        '<th colspan="2">Difference between the two results</th><th colspan="2">Status</th></tr>'
        "<tr><th>Proposed method</th><th>Manual method</th><th>Rotation (deg)</th><th>Translation (cm)</th>"
        "<th>Proposed</th><th>Manual</th></tr>" + "".join(rows) + "</table>"
    )
    auto_r, manual_r = comparison.get("auto_target_residual_m"), comparison.get("manual_target_residual_m")
    targets = comparison.get("targets") if isinstance(comparison.get("targets"), Mapping) else {}
    t_auto = targets.get("auto") if isinstance(targets.get("auto"), Mapping) else {}
    t_manual = targets.get("manual") if isinstance(targets.get("manual"), Mapping) else {}
    out.append("<h3>Per plot (paper table 5)</h3>")
    out.append(
        "<table><tr><th>Plot</th><th>Proposed method (cm)</th><th>Manual method (cm)</th><th>Targets seen twice</th></tr>"
        f'<tr><td>average target distance residual</td><td class="num"><b>{format_cm(auto_r)}</b></td>'
        f'<td class="num"><b>{format_cm(manual_r)}</b></td>'
        f'<td class="num">{_e(str(len(set(t_auto) | set(t_manual))))}</td></tr></table>'
        '<p class="note">With every scan in the project frame, the mean distance between the centres of the same target '
        "seen from different scans.</p>"
        + (
            f'<p class="note"><b>Not available:</b> {_e(comparison["target_residual_note"])}</p>'
            if comparison.get("target_residual_note")
            else ""
        )
    )
    if pairs and any(v is not None for v in s_auto + s_manual):
        png = _bars_png(
            BarPanel(
                labels,
                [("proposed (marker-free)", s_auto, AUTO_COLOUR), ("manual (targets)", s_manual, MANUAL_COLOUR)],
                "ICP standard deviation (cm)",
                "ICP standard deviation per pair",
            ),
        )
        png2 = (
            None
            if all(v is None for v in trans + rot)
            else _bars_png(
                BarPanel(
                    labels,
                    [("translation", trans, "#6a51a3")],
                    "translation difference (cm)",
                    "Proposed against manual: translation",
                ),
                BarPanel(
                    labels,
                    [("rotation", rot, "#fd8d3c")],
                    "rotation difference (deg)",
                    "Proposed against manual: rotation",
                    digits=3,
                ),
            )
        )
        diff_img = "" if png2 is None else _img(png2, "difference per pair", "cmpdiff")
        out.append(
            f"<figure>{_img(png, 'ICP std per pair, proposed and manual', 'cmppairs')}{diff_img}"
            "<figcaption>Per pair: the ICP standard deviation of both methods, and how far apart the two results are "
            "(rotation in degrees, translation at the moving scanner in cm).</figcaption></figure>"
        )
    ids = sorted(set(t_auto) | set(t_manual), key=_natural)
    if ids:
        va = [100.0 * t_auto[i] if _num(t_auto.get(i)) else None for i in ids]
        vm = [100.0 * t_manual[i] if _num(t_manual.get(i)) else None for i in ids]
        rows = "".join(
            f'<tr><td>{_e(str(i))}</td><td class="num">{format_cm(t_auto.get(i))}</td><td class="num">{format_cm(t_manual.get(i))}</td></tr>'
            for i in ids
        )
        out.append(
            "<table><tr><th>Target</th><th>Proposed method (cm)</th><th>Manual method (cm)</th></tr>"
            + rows
            + "</table>"
        )
        png = _bars_png(
            BarPanel(
                [str(i) for i in ids],
                [("proposed (marker-free)", va, AUTO_COLOUR), ("manual (targets)", vm, MANUAL_COLOUR)],
                "mean distance residual (cm)",
                "Target distance residual per target: proposed against manual",
            )
        )
        out.append(
            f"<figure>{_img(png, 'target residual per target', 'cmptargets')}"
            "<figcaption>Per target: the mean distance between its centres seen from different scans, with the scans "
            "placed by each method.</figcaption></figure>"
        )
    return "\n".join(out)


def _parameters_section(project: Project) -> str:
    params = project.params
    default = RegistrationParams()
    cells = []
    for f in dataclasses.fields(RegistrationParams):
        value = getattr(params, f.name)
        unit = f.metadata.get("unit", "")
        paper = f.metadata.get("paper", "")
        changed = value != getattr(default, f.name)
        text = _param_value(value) + (f" {unit}" if unit and unit != "1" and value is not None else "")
        cells.append(
            f'<td title="{_e(f.metadata.get("help", ""))}"><code>{_e(f.name)}</code>'
            + (f'<br><span class="note">{_e(paper)}</span>' if paper else "")
            + f'</td><td class="{"changed" if changed else ""}">{_e(text)}</td>'
        )
    per_row = 3
    rows = "".join("<tr>" + "".join(cells[i : i + per_row]) + "</tr>" for i in range(0, len(cells), per_row))
    head = "<tr>" + "<th>Parameter</th><th>Value</th>" * per_row + "</tr>"
    out = [
        "<h2>Parameters</h2>",
        '<p class="note">The project\'s registration parameters (paper table 2 where it gives a value; hover a name '
        'for its meaning). Values changed from the defaults are shown <span class="changed">like this</span>.</p>',
        "<table>" + head + rows + "</table>",
    ]
    overrides = []
    for link in project.links:
        bits = []
        if link.vop_radius_m is not None:
            bits.append(f"D_r {link.vop_radius_m:g} m")
        if link.slice_offsets_m is not None:
            bits.append("slice offsets " + ", ".join(f"{v:g}" for v in link.slice_offsets_m) + " m")
        if bits:
            overrides.append(f"<li>{_e(_link_label(link))}: {_e('; '.join(bits))}</li>")
    if overrides:
        out.append("<p>Per-link overrides:</p><ul>" + "".join(overrides) + "</ul>")
    return "\n".join(out)


# ------------------------------------------------------------------------------------------------
# formatting
# ------------------------------------------------------------------------------------------------


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _num(value: Any) -> bool:
    return (
        isinstance(value, (int, float, np.integer, np.floating))
        and not isinstance(value, bool)
        and math.isfinite(float(value))
    )


def _fmt(value: Any, digits: int, scale: float = 1.0, *, thousands: bool = False) -> str:
    """A number for a table cell (a dash where missing)."""
    if not _num(value):
        return DASH
    v = float(value) * scale
    return f"{v:,.{digits}f}" if thousands else f"{v:.{digits}f}"


def format_cm(value_m: Any) -> str:
    """Metres shown in centimetres with two decimals, as in the report's tables ("2.00")."""
    return _fmt(value_m, 2, 100.0)


def _status_html(status: Any) -> str:
    if status is None:
        return DASH
    s = str(status)
    return f'<span class="{"ok" if s == "ok" else "bad"}">{_e(s)}</span>'


def _param_value(value: Any) -> str:
    if value is None:
        return "auto"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, (tuple, list)):
        return ", ".join(_param_value(v) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _short(text: str, n: int) -> str:
    """Text for a figure: shortened, and with ``$`` escaped (no accidental mathtext)."""
    text = str(text)
    text = text if len(text) <= n else text[: n - 1] + "\u2026"
    return text.replace("$", r"\$")


def _natural(key: Any) -> tuple:
    import re

    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(key)))


def _version() -> str:
    try:
        from ..._version import __version__

        return str(__version__)
    except Exception:  # pragma: no cover - defensive
        return "?"


__all__ = [
    "write_plot_report",
    "plot_report_html",
    "top_view_png",
    "compute_top_view",
    "comparison_section",
    "scan_states",
    "scan_colours",
    "format_cm",
]
