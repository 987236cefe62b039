"""HTML report of the trees of a plot (System B output, paper section 4.3).

:func:`write_trees_report` writes ``report.html`` (self-contained, figures embedded as base64 PNG,
matplotlib Agg) and the same PNGs into ``figures/``:

1. a plot map: top view of the points coloured by tree, each stem's position with a circle of
   its DBH (scaled up to be visible; the factor is printed), tree ids, flagged trees in red;
2. a summary (counts, means, totals), and where the inventory has one, the heights against the
   plot's height-diameter curve (each tree coloured by the trust of its height);
3. a table with one row per tree;
4. per tree a figure: a side view (x against z) of its points, wood brown and leaves green, and
   beside it the cylinder model projected on the same plane, each cylinder a band of width 2r
   along its axis, coloured by branch order.

Frames: whatever frame the inputs share (plot frame, metres; z as given, e.g. height above
ground). The number of per-tree figures and of points drawn are capped so the file stays small
(about 20 MB at most); trees beyond the cap are listed without a figure.
"""

from __future__ import annotations

import io
import math
import os
import re
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.patches import Circle, Patch  # noqa: E402

from ..core.atomic import atomic_path, write_text_atomic  # noqa: E402
from ..core.errors import ScanDataError  # noqa: E402
from ..core.scan import check_points
from .evaluation_report import DASH, esc, fmt, generated_line, html_page, img_tag, png_bytes  # noqa: E402
from .raster import PointRaster, add_points  # noqa: E402

#: Per-tree figures drawn at most (the rest of the trees are listed without one).
MAX_TREE_FIGURES = 60
#: Points drawn on the plot map at most.
MAX_MAP_POINTS = 150_000
#: Points drawn per tree figure at most.
MAX_TREE_POINTS = 15_000
#: A point with at least this wood probability is drawn as wood.
WOOD_THRESHOLD = 0.5
WOOD_COLOUR = "#8c510a"
LEAF_COLOUR = "#1a9850"
UNCLASSIFIED_COLOUR = "0.45"
FLAG_COLOUR = "#d62728"
#: Cylinder colours by branch order: 0 = stem, 1, 2, 3, 4, 5 and more.
ORDER_COLOURS = ("#5d3a1a", "#d95f02", "#1b9e77", "#7570b3", "#e7298a", "#66a61e")
CYLINDER_COLUMNS = ("start_x", "start_y", "start_z", "axis_x", "axis_y", "axis_z", "length_m", "radius_m")
#: Table columns: key, heading, scale, decimals.
TABLE_COLUMNS = (
    ("x", "x (m)", 1.0, 2),
    ("y", "y (m)", 1.0, 2),
    ("dbh_m", "DBH (cm)", 100.0, 1),
    ("height_m", "H (m)", 1.0, 2),
    ("crown_base_m", "CBH (m)", 1.0, 2),
    ("crown_area_m2", "CA (m²)", 1.0, 2),
    ("crown_volume_m3", "CV (m³)", 1.0, 2),
    ("volume_m3", "V (m³)", 1.0, 3),
)
_RNG_SEED = 7

#: the table's mark of a height not the points' own, by ``height_source``
_HEIGHT_MARK = {"curve": "<sup>c</sup>", "slenderness": "<sup>s</sup>"}


def write_inventory_report(
    out_dir: str | os.PathLike[str], inventory: Any, points: np.ndarray, *, title: str = "forestreg trees"
) -> Path:
    """:func:`write_trees_report` of a tree inventory (``rows()``, ``trees``, ``labels``,
    ``wood_probability``, ``origin_shift``) and the cloud it was measured in (local frame)."""
    shift = np.asarray(inventory.origin_shift, dtype=np.float64)
    cyl = {t.tree_id: t.cylinders.to_table() for t in inventory.trees if t.cylinders is not None}
    rows = [{**r, "x": r["x"] - shift[0], "y": r["y"] - shift[1]} for r in inventory.rows()]
    wood = inventory.wood_probability
    if len(wood) and np.isnan(wood[0]) and np.isnan(wood).all():  # not measured (no cylinder models): grey
        wood = None
    return write_trees_report(
        out_dir,
        rows,
        points,
        inventory.labels,
        wood,
        cyl,
        title=title,
        height_curve=getattr(inventory, "height_curve", None),
        stations=getattr(inventory, "stations", None),
    )


def write_trees_report(
    out_dir: str | os.PathLike[str],
    trees: Sequence[Mapping[str, Any]],
    points: np.ndarray,
    tree_ids: np.ndarray,
    wood_probability: Optional[np.ndarray],
    cylinders: Mapping[int, Mapping[str, np.ndarray]],
    title: Optional[str] = None,
    *,
    max_tree_figures: int = MAX_TREE_FIGURES,
    dbh_scale: Optional[float] = None,
    height_curve: Optional[Any] = None,
    stations: Optional[Any] = None,
) -> Path:
    """Write ``out_dir/report.html`` and ``out_dir/figures/*.png``; return the HTML's path.

    Parameters
    ----------
    trees : one mapping per tree: ``tree_id`` (int, as in ``tree_ids``), ``x``, ``y`` (stem
        position, m), ``dbh_m``, ``height_m``, ``crown_base_m``, ``crown_area_m2``,
        ``crown_volume_m3``, ``volume_m3`` (missing or None shown as a dash) and ``flag`` (empty,
        None, False or "ok" = no problem; any other text is shown and the tree marked).
    points : (N, 3) points of the plot (metres).
    tree_ids : (N,) int, the tree of each point (0 = none).
    wood_probability : (N,) in [0, 1] or None (points then drawn in grey).
    cylinders : per tree id a cylinder table: arrays ``start_x, start_y, start_z`` (m),
        ``axis_x, axis_y, axis_z`` (unit direction), ``length_m``, ``radius_m`` and optionally
        ``branch_order`` (0 = stem); other columns are ignored.
    title : the report's title.
    max_tree_figures : per-tree figures drawn at most (by tree id order).
    dbh_scale : factor the DBH circles of the map are enlarged by; default chosen from the plot
        size (printed on the map).
    height_curve : the plot's height-diameter curve (:class:`forestreg.engine.trees.allometry.HeightCurve`:
        ``height_m(dbh_m)`` and ``describe()``), drawn with the trees' heights; None: no such figure.
    stations : the terrestrial scanner stations found in the cloud
        (:class:`forestreg.engine.tls.stations.Stations`: ``positions`` (K, 3) in the frame of
        ``points`` and ``describe()``), drawn on the map and named under it; None: not looked for.
    """
    pts = check_points(points, "points", min_points=0)
    ids = np.asarray(tree_ids)
    if ids.shape != (len(pts),):
        raise ScanDataError(f"tree_ids: expected one id per point ({len(pts)}), got shape {ids.shape}")
    ids = ids.astype(np.int64)
    wood = None
    if wood_probability is not None:
        wood = np.asarray(wood_probability, dtype=np.float64)
        if wood.shape != (len(pts),):
            raise ScanDataError(f"wood_probability: expected one value per point ({len(pts)}), got shape {wood.shape}")
    rows = [_clean_row(r, k) for k, r in enumerate(trees)]
    title = title or "forestreg: trees of the plot"
    out = Path(out_dir)
    fig_dir = out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)

    groups = _group_points(ids)
    station_xy = np.asarray(stations.positions, dtype=np.float64)[:, :2] if stations is not None else np.zeros((0, 2))
    map_png, scale = _map_png(pts, ids, rows, dbh_scale, station_xy)
    _write_png(fig_dir / "map.png", map_png)

    curve_section = ""
    if height_curve is not None:
        curve_png = _height_curve_png(rows, height_curve)
        _write_png(fig_dir / "height_curve.png", curve_png)
        curve_section = (
            "<figure>"
            + img_tag(curve_png, "heights against the height-diameter curve", "curve")
            + "<figcaption>Height against DBH: each tree coloured by its height's trust (black high: its top stands clear; "
            "orange medium: a hint about its top, its height consistent with the curve or its apex a tip; red low: flagged; blue squares: "
            "heights predicted from the curve where the points' top was hidden or a neighbour's, a dot at that top). The line is the "
            f"plot's height-diameter curve, {esc(height_curve.describe())}; dashed, {100 * height_curve.widest_below:.0f} % below "
            f"and {100 * height_curve.above:.0f} % above it (the widest allowance, for a top standing clear over its stem; "
            "a top with a hint about it, under a neighbour's crown, on the crown's flank or not seen, is allowed less).</figcaption></figure>"
        )
    drawn: dict[str, bytes] = {}
    order = sorted(rows, key=lambda r: _natural(r["tree_id"]))
    problems: list[str] = []
    figure = _TreeFigure(models=bool(cylinders))
    try:
        for row in order[: max(0, int(max_tree_figures))]:
            tid = row["tree_id"]
            sel = groups.get(_int_id(tid), np.zeros(0, dtype=np.int64))
            cyl, issue = _cylinder_table(cylinders, tid)
            if issue:
                problems.append(f"tree {tid}: {issue}")
            png = figure.png(row, pts[sel], None if wood is None else wood[sel], cyl)
            drawn[str(tid)] = png
            _write_png(fig_dir / f"tree_{_file_stem(str(tid))}.png", png)
    finally:
        figure.close()

    body = [
        f"<h1>{esc(title)}</h1>",
        f'<p class="sub">{len(rows)} trees &middot; {len(pts):,} points &middot; {esc(generated_line())}</p>',
        "<h2>1. Plot map</h2>",
        f"<figure>{img_tag(map_png, 'plot map', 'map')}<figcaption>Top view: points coloured by tree (grey: no tree), "
        f"stem positions (+) with circles of the DBH enlarged {_scale_text(scale)}, tree ids; flagged trees in red"
        + (f"; scanner stations (blue triangles): {esc(stations.describe())}" if station_xy.size else "")
        + ".</figcaption></figure>",
        _summary_section(rows, ids, wood) + curve_section,
        _table_section(rows, set(drawn)),
        _trees_section(order, drawn, max_tree_figures, problems, models=bool(cylinders), wood=wood is not None),
    ]
    path = out / "report.html"
    write_text_atomic(path, html_page(title, body))
    return path


# ------------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------------


def _clean_row(row: Mapping[str, Any], k: int) -> dict[str, Any]:
    if "tree_id" not in row:
        raise ScanDataError(f"trees: row {k + 1} has no tree_id")
    out: dict[str, Any] = {"tree_id": row["tree_id"]}
    for key, *_ in TABLE_COLUMNS:
        out[key] = _num(row.get(key))
    flag = row.get("flag")
    if flag is None or flag is False or (isinstance(flag, float) and math.isnan(flag)):
        out["flag"] = ""
    else:
        text = str(flag).strip()
        out["flag"] = "" if text.lower() in ("", "ok", "false", "0", "none") else text
    # trust of each measure: the part after the last "; " of its quality column (if given)
    out["trust"] = {m: str(row.get(f"{m}_quality") or "").rsplit("; ", 1)[-1] for m in QUALITY_MEASURES}
    out["height_source"] = str(row.get("height_source") or "points")
    out["height_points_m"] = _num(row.get("height_points_m"))
    return out


#: Measures with a quality column ``<measure>_quality`` (``"<how>; <trust>"``) in trees.csv.
QUALITY_MEASURES = ("dbh", "height", "crown", "volume")


def _num(value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return float("nan")
    return v if math.isfinite(v) else float("nan")


def _int_id(tid: Any) -> Optional[int]:
    try:
        return int(tid)
    except (TypeError, ValueError):
        return None


def _group_points(ids: np.ndarray) -> dict[int, np.ndarray]:
    """Indices of the points of each tree id (> 0)."""
    order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    starts = np.flatnonzero(np.r_[True, sorted_ids[1:] != sorted_ids[:-1]]) if len(ids) else np.zeros(0, int)
    bounds = np.r_[starts, len(ids)]
    out: dict[int, np.ndarray] = {}
    for a, b in zip(bounds[:-1], bounds[1:]):
        tid = int(sorted_ids[a])
        if tid > 0:
            out[tid] = order[a:b]
    return out


def _cylinder_table(
    cylinders: Mapping[Any, Mapping[str, np.ndarray]], tid: Any
) -> tuple[Optional[dict[str, np.ndarray]], str]:
    table = (
        cylinders.get(tid) if tid in cylinders else cylinders.get(_int_id(tid)) if _int_id(tid) in cylinders else None
    )
    if table is None:
        return None, ""
    missing = [c for c in CYLINDER_COLUMNS if c not in table]
    if missing:
        return None, f"cylinder table lacks {', '.join(missing)}"
    cols = {c: np.asarray(table[c], dtype=np.float64) for c in CYLINDER_COLUMNS}
    n = len(cols["start_x"])
    order = np.asarray(table["branch_order"], dtype=np.float64) if "branch_order" in table else np.zeros(n)
    if any(len(v) != n for v in cols.values()) or len(order) != n:
        raise ScanDataError(f"tree {tid}: the columns of its cylinder table differ in length")
    cols["branch_order"] = order
    ok = np.all([np.isfinite(v) for v in cols.values()], axis=0) if n else np.zeros(0, bool)
    return {k: v[ok] for k, v in cols.items()}, (
        "" if ok.all() else f"{int((~ok).sum())} cylinders with missing values not drawn"
    )


# ------------------------------------------------------------------------------------------------
# figures
# ------------------------------------------------------------------------------------------------


#: Tree colours of the map: tab20 without its reds (the flag colour) and greys (points in no tree).
_TREE_PALETTE = np.array([plt.get_cmap("tab20")(i) for i in (0, 2, 4, 8, 10, 12, 16, 18, 1, 3, 5, 9, 11, 13, 17, 19)])


_TREE_PALETTE_BYTES = (_TREE_PALETTE * 255.0 + 0.5).astype(np.uint8)


def _tree_colours(ids: np.ndarray) -> np.ndarray:
    """(N, 4) RGBA bytes of the trees ``ids`` (the palette repeats every 16 trees)."""
    return _TREE_PALETTE_BYTES[np.mod(ids, len(_TREE_PALETTE))].reshape(-1, 4)


def _auto_scale(rows: Sequence[Mapping[str, Any]], extent: float) -> float:
    radii = np.array([r["dbh_m"] / 2 for r in rows if math.isfinite(r["dbh_m"]) and r["dbh_m"] > 0])
    if not len(radii) or extent <= 0:
        return 1.0
    fits = [s for s in (1, 2, 5, 10, 20, 50) if s * float(np.median(radii)) <= 0.015 * extent]
    return float(fits[-1]) if fits else 1.0


def _scale_text(scale: float) -> str:
    return "to scale" if scale == 1 else f"{scale:g} times"


def _map_png(
    pts: np.ndarray,
    ids: np.ndarray,
    rows: Sequence[Mapping[str, Any]],
    dbh_scale: Optional[float],
    stations: np.ndarray = np.zeros((0, 2)),
) -> tuple[bytes, float]:
    rng = np.random.default_rng(_RNG_SEED)
    sel = (
        np.arange(len(pts))
        if len(pts) <= MAX_MAP_POINTS
        else np.sort(rng.choice(len(pts), MAX_MAP_POINTS, replace=False))
    )
    p, t = pts[sel, :2], ids[sel]
    stems = np.array([[r["x"], r["y"]] for r in rows if math.isfinite(r["x"]) and math.isfinite(r["y"])]).reshape(-1, 2)
    corners = np.vstack([p.min(axis=0), p.max(axis=0)] if len(p) else np.zeros((0, 2)))
    xy_all = np.vstack([corners, stems]) if len(p) or len(stems) else np.zeros((1, 2))
    extent = float(np.ptp(xy_all, axis=0).max()) if len(xy_all) > 1 else 1.0
    scale = float(dbh_scale) if dbh_scale else _auto_scale(rows, extent)
    fig, ax = plt.subplots(figsize=(9.5, 9.0))
    none = t <= 0
    size = float(np.clip(4.0e4 / max(len(p), 1), 0.6, 4.0))
    add_points(ax, [(p[none], "0.8", size * 0.7), (p[~none], _tree_colours(t[~none]), size)])
    fontsize = 8 if len(rows) <= 60 else 6 if len(rows) <= 200 else 4
    for r in rows:
        if not (math.isfinite(r["x"]) and math.isfinite(r["y"])):
            continue
        colour = FLAG_COLOUR if r["flag"] else "k"
        if math.isfinite(r["dbh_m"]) and r["dbh_m"] > 0:
            ax.add_patch(
                Circle((r["x"], r["y"]), r["dbh_m"] / 2 * scale, fill=False, ec=colour, lw=2.0 if r["flag"] else 0.9)
            )
        ax.plot(r["x"], r["y"], marker="x" if r["flag"] else "+", color=colour, ms=7, mew=1.6 if r["flag"] else 1.0)
        if r["flag"]:
            ax.plot(r["x"], r["y"], marker="o", mfc="none", mec=FLAG_COLOUR, ms=16, mew=2.0)
        ax.annotate(
            str(r["tree_id"]) + (" !" if r["flag"] else ""),
            (r["x"], r["y"]),
            xytext=(9, 7) if r["flag"] else (4, 4),
            textcoords="offset points",
            fontsize=fontsize,
            color=colour,
            fontweight="bold" if r["flag"] else "normal",
        )
    handles = [
        plt.Line2D(
            [], [], ls="", marker="o", mfc="none", mec="k", ms=8, label=f"stem, DBH circle ({_scale_text(scale)})"
        ),
        plt.Line2D([], [], ls="", marker="o", mfc="none", mec=FLAG_COLOUR, ms=10, mew=2.0, label="flagged tree"),
    ]
    if len(stations):
        ax.plot(stations[:, 0], stations[:, 1], ls="", marker="^", color="tab:blue", mec="k", ms=11, zorder=5)
        handles.append(
            plt.Line2D([], [], ls="", marker="^", color="tab:blue", mec="k", ms=9, label="scanner station (found)")
        )
    ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.9)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"Plot map: {len(rows)} trees", fontsize=11)
    ax.grid(True, lw=0.3)
    fig.tight_layout()
    return png_bytes(fig, 100), scale


def _height_curve_png(rows: Sequence[Mapping[str, Any]], curve: Any) -> bytes:
    """DBH (cm) against height (m) of every tree with both, coloured by the height's trust, over
    the plot's height-diameter curve and its widest allowance."""
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    d = np.array([r["dbh_m"] for r in rows], dtype=np.float64)
    h = np.array([r["height_m"] for r in rows], dtype=np.float64)
    trust = np.array([r["trust"].get("height", "") for r in rows])
    ok = np.isfinite(d) & np.isfinite(h) & (d > 0)
    if ok.any():
        grid = np.linspace(max(0.02, 0.8 * d[ok].min()), 1.1 * d[ok].max(), 100)
        line = np.array([curve.height_m(x) for x in grid])
        ax.plot(100 * grid, line, color="k", lw=1.4, label="height-diameter curve")
        lo, hi = 1.0 - curve.widest_below, 1.0 + curve.above
        ax.plot(
            100 * grid,
            lo * line,
            color="k",
            lw=0.8,
            ls="--",
            label=f"-{100 * curve.widest_below:.0f} % / +{100 * curve.above:.0f} %",
        )
        ax.plot(100 * grid, hi * line, color="k", lw=0.8, ls="--")
    fill = np.array([r["height_source"] != "points" for r in rows])
    top = np.array([r["height_points_m"] for r in rows], dtype=np.float64)
    for level, colour, marker, label in (
        ("high", "k", "o", "high"),
        ("medium", "#ff7f00", "o", "medium (a hint about the top, weighed: the top stands)"),
        ("low", FLAG_COLOUR, "x", "low (flagged)"),
    ):
        sel = ok & (trust == level) & ~fill
        if sel.any():
            ax.plot(
                100 * d[sel],
                h[sel],
                ls="",
                marker=marker,
                color=colour,
                ms=6,
                mew=1.6,
                label=f"{label}: {int(sel.sum())}",
            )
    sel = ok & fill
    if sel.any():
        # the curve's height, and a thin line to the points' top it stands in for
        for x, a, b in zip(100 * d[sel], h[sel], top[sel]):
            if math.isfinite(b):
                ax.plot([x, x], [a, b], color="#1f77b4", lw=0.7, alpha=0.7)
        ax.plot(100 * d[sel], top[sel], ls="", marker=".", color="#1f77b4", ms=4)
        ax.plot(
            100 * d[sel],
            h[sel],
            ls="",
            marker="s",
            mfc="none",
            color="#1f77b4",
            ms=6,
            mew=1.4,
            label=f"estimated: {int(sel.sum())} (dot: the points' top, not taken)",
        )
    ax.set_xlabel("DBH (cm)")
    ax.set_ylabel("height (m)")
    ax.set_title("Heights and the plot's height-diameter curve", fontsize=11)
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=8, loc="lower right", framealpha=0.9)
    fig.tight_layout()
    return png_bytes(fig, 100)


def cylinder_polygons(cyl: Mapping[str, np.ndarray], axes: tuple[int, int] = (0, 2)) -> np.ndarray:
    """(M, 4, 2) outlines of cylinders projected on the plane of two coordinate axes
    (0 = x, 1 = y, 2 = z): a band of width 2r from the start to the end of the axis (a square
    of side 2r where the axis points straight at the viewer)."""
    start = np.c_[cyl["start_x"], cyl["start_y"], cyl["start_z"]][:, list(axes)]
    direction = np.c_[cyl["axis_x"], cyl["axis_y"], cyl["axis_z"]]
    norm = np.linalg.norm(direction, axis=1)
    direction = direction / np.where(norm > 0, norm, 1.0)[:, None]
    end = start + (direction * cyl["length_m"][:, None])[:, list(axes)]
    d = end - start
    length = np.linalg.norm(d, axis=1)
    r = np.asarray(cyl["radius_m"], dtype=np.float64)
    flat = length < 1e-9
    u = np.where(flat[:, None], np.array([1.0, 0.0]), d / np.where(flat, 1.0, length)[:, None])
    n = np.c_[-u[:, 1], u[:, 0]] * r[:, None]
    start = np.where(flat[:, None], start - u * r[:, None], start)
    end = np.where(flat[:, None], start + 2 * u * r[:, None], end)
    return np.stack([start + n, end + n, end - n, start - n], axis=1)


class _TreeFigure:
    """The per-tree figure (points coloured leaf / wood beside the cylinder model, side view x-z,
    the same window on both), made once and redrawn for every tree: a figure of its own per tree,
    laid out by ``tight_layout``, cost 0.13 s a tree; the layout is fixed instead (both panels keep
    equal axes, centred in their halves). ``models`` False (no tree of the report has a cylinder
    model: none asked for): the points' panel alone, half the drawing."""

    def __init__(self, models: bool = True) -> None:
        if models:
            self.fig, (self.ax_p, self.ax_c) = plt.subplots(1, 2, figsize=(9.0, 5.6))
            self.fig.subplots_adjust(left=0.08, right=0.98, bottom=0.1, top=0.88, wspace=0.2)
        else:
            self.fig, self.ax_p = plt.subplots(figsize=(6.0, 5.6))
            self.fig.subplots_adjust(left=0.12, right=0.97, bottom=0.1, top=0.86)
            self.ax_c = None
        for ax in self.axes:
            ax.set_aspect("equal", adjustable="box")
            ax.set_xlabel("x (m)")
            ax.grid(True, lw=0.3)
        self.ax_p.set_ylabel("z (m)")
        self._tree_artists: list[Any] = []

    @property
    def axes(self) -> tuple[Any, ...]:
        """The panels: the points', and the cylinder model's when drawn."""
        return (self.ax_p,) if self.ax_c is None else (self.ax_p, self.ax_c)

    def close(self) -> None:
        plt.close(self.fig)

    def png(
        self,
        row: Mapping[str, Any],
        pts: np.ndarray,
        wood: Optional[np.ndarray],
        cyl: Optional[Mapping[str, np.ndarray]],
    ) -> bytes:
        """PNG bytes of one tree: ``pts`` (N, 3) its points (metres), ``wood`` their wood
        probability or None, ``cyl`` its cylinder table or None."""
        for artist in self._tree_artists:  # the previous tree's
            artist.remove()
        drawn = self._tree_artists = []
        ax_p, ax_c = self.ax_p, self.ax_c
        rng = np.random.default_rng(_RNG_SEED)
        if len(pts) > MAX_TREE_POINTS:
            keep = np.sort(rng.choice(len(pts), MAX_TREE_POINTS, replace=False))
            pts = pts[keep]
            wood = None if wood is None else wood[keep]
        extent = [pts[:, [0, 2]]] if len(pts) else []
        if len(pts):
            if wood is None:
                drawn.append(ax_p.add_artist(PointRaster([(pts[:, [0, 2]], UNCLASSIFIED_COLOUR, 0.6)])))
            else:
                is_wood = wood >= WOOD_THRESHOLD
                drawn.append(
                    ax_p.add_artist(
                        PointRaster(
                            [(pts[~is_wood][:, [0, 2]], LEAF_COLOUR, 0.6), (pts[is_wood][:, [0, 2]], WOOD_COLOUR, 0.8)]
                        )
                    )
                )
                drawn.append(
                    ax_p.legend(
                        handles=[
                            plt.Line2D([], [], ls="", marker="o", ms=4, color=c, label=name)
                            for c, name in ((LEAF_COLOUR, "leaf"), (WOOD_COLOUR, "wood"))
                        ],
                        loc="upper right",
                        fontsize=7,
                    )
                )
        else:
            drawn.append(
                ax_p.text(0.5, 0.5, "no points", transform=ax_p.transAxes, ha="center", va="center", color="0.4")
            )
        n_cyl = 0
        if ax_c is None:
            pass
        elif cyl is not None and len(cyl["start_x"]):
            polys = cylinder_polygons(cyl)
            order = np.clip(np.asarray(cyl["branch_order"]).astype(int), 0, len(ORDER_COLOURS) - 1)
            draw = np.argsort(order, kind="stable")  # stem first, higher orders on top
            drawn.append(
                ax_c.add_collection(
                    PolyCollection(polys[draw], facecolors=[ORDER_COLOURS[o] for o in order[draw]], edgecolors="none"),
                    autolim=False,
                )
            )
            extent.append(polys.reshape(-1, 2))
            n_cyl = len(polys)
            present = sorted(set(order.tolist()))
            drawn.append(
                ax_c.legend(
                    handles=[
                        Patch(
                            color=ORDER_COLOURS[o],
                            label="stem" if o == 0 else f"order {o}" + ("+" if o == len(ORDER_COLOURS) - 1 else ""),
                        )
                        for o in present
                    ],
                    loc="upper right",
                    fontsize=7,
                )
            )
        else:
            drawn.append(
                ax_c.text(
                    0.5, 0.5, "no cylinder model", transform=ax_c.transAxes, ha="center", va="center", color="0.4"
                )
            )
        if extent:  # the same window on both panels
            xz = np.vstack(extent)
            lo, hi = xz.min(axis=0), xz.max(axis=0)
            pad = 0.05 * float((hi - lo).max()) + 0.2
            window = ((lo[0] - pad, hi[0] + pad), (lo[1] - pad, hi[1] + pad))
        else:
            window = ((0.0, 1.0), (0.0, 1.0))
        for ax in self.axes:
            ax.set_xlim(*window[0])
            ax.set_ylim(*window[1])
        # at the top of the axes, where matplotlib would place them (nothing stands above the
        # axes): placed so, a draw does not measure every tick label to place them
        ax_p.set_title(f"points ({len(pts):,} drawn)", fontsize=9, y=1.0)
        if ax_c is not None:
            ax_c.set_title(f"cylinder model ({n_cyl} cylinders, width 2r)", fontsize=9, y=1.0)
        head = f"Tree {row['tree_id']}: DBH {fmt(row['dbh_m'], 1, 100.0)} cm, H {fmt(row['height_m'], 2)} m, V {fmt(row['volume_m3'], 3)} m³"
        if row["flag"]:
            head += ("  " if ax_c is not None else "\n") + f"[{row['flag'][:60]}]"
        self.fig.suptitle(head.replace("$", r"\$"), fontsize=10, color=FLAG_COLOUR if row["flag"] else "k")
        buf = io.BytesIO()
        self.fig.savefig(buf, format="png", dpi=80)
        return buf.getvalue()


def _write_png(path: Path, png: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(png)


# ------------------------------------------------------------------------------------------------
# HTML sections
# ------------------------------------------------------------------------------------------------


def _summary_section(rows: Sequence[Mapping[str, Any]], ids: np.ndarray, wood: Optional[np.ndarray]) -> str:
    def stat(key: str, scale: float, digits: int) -> str:
        v = np.array([r[key] for r in rows], dtype=np.float64)
        v = v[np.isfinite(v)]
        if not len(v):
            return f'<td class="num">{DASH}</td>' * 3
        return "".join(f'<td class="num">{fmt(x, digits, scale)}</td>' for x in (v.mean(), v.min(), v.max()))

    flagged = sum(1 for r in rows if r["flag"])
    assigned = int((ids > 0).sum())
    vol = np.array([r["volume_m3"] for r in rows], dtype=np.float64)
    total_v = float(vol[np.isfinite(vol)].sum()) if np.isfinite(vol).any() else None
    wood_share = float((wood[ids > 0] >= WOOD_THRESHOLD).mean()) if wood is not None and assigned else None
    lines = [
        "<h2>2. Summary</h2>",
        "<table><tr><th>Trees</th><th>Flagged</th><th>Points in trees</th><th>Wood share of tree points</th><th>Total wood volume (m³)</th></tr>"
        f'<tr><td class="num">{len(rows)}</td><td class="num">{flagged}</td>'
        f'<td class="num">{assigned:,} of {len(ids):,}</td><td class="num">{fmt(wood_share, 1, 100.0)} %</td>'
        f'<td class="num">{fmt(total_v, 3)}</td></tr></table>',
        "<table><tr><th>Parameter</th><th>Mean</th><th>Min</th><th>Max</th></tr>",
    ]
    for key, head, scale, digits in TABLE_COLUMNS[2:]:
        lines.append(f"<tr><td>{esc(head)}</td>{stat(key, scale, digits)}</tr>")
    lines.append("</table>")
    return "\n".join(lines)


def _table_section(rows: Sequence[Mapping[str, Any]], drawn: set[str]) -> str:
    head = (
        "<tr><th>Tree</th>"
        + "".join(f"<th>{esc(h)}</th>" for _, h, _, _ in TABLE_COLUMNS)
        + "<th>Trust (DBH / H / crown / V)</th><th>Flag</th></tr>"
    )
    body = []
    for r in sorted(rows, key=lambda r: _natural(r["tree_id"])):
        tid = str(r["tree_id"])
        name = f'<a href="#tree-{esc(_file_stem(tid))}">{esc(tid)}</a>' if tid in drawn else esc(tid)
        # a height from the plot's height-diameter curve is marked "c"
        cells = "".join(
            f'<td class="num">{fmt(r[k], d, s)}'
            + (_HEIGHT_MARK.get(r["height_source"], "") if k == "height_m" else "")
            + "</td>"
            for k, _, s, d in TABLE_COLUMNS
        )
        flag = f'<span class="bad">{esc(r["flag"])}</span>' if r["flag"] else ""
        trust = r.get("trust") or {}
        trust_cell = " / ".join(esc(trust.get(m) or "-") for m in QUALITY_MEASURES)
        body.append(
            f'<tr class="{"flagged" if r["flag"] else ""}" id="row-{esc(_file_stem(tid))}"><td>{name}</td>{cells}<td>{trust_cell}</td><td>{flag}</td></tr>'
        )
    return (
        "<h2>3. Trees</h2><table>" + head + "".join(body) + "</table>"
        '<p class="note">DBH: diameter at breast height (1.3 m); H: height (<sup>c</sup>: from the plot\'s height-diameter '
        "curve, the points' top hidden or a neighbour's; <sup>s</sup>: at most the tallest its stem stands, the points' top "
        "too tall for it); CBH: crown base height; CA: crown projection area; "
        "CV: crown volume; V: wood volume of the cylinder model. Trust of each measure (high, medium, low, none; how it was "
        "obtained is in trees.csv's quality columns). Flagged trees (red) need a look: the flag says why.</p>"
    )


def _trees_section(
    order: Sequence[Mapping[str, Any]],
    drawn: Mapping[str, bytes],
    cap: int,
    problems: Sequence[str],
    *,
    models: bool = True,
    wood: bool = True,
) -> str:
    note = (
        '<p class="note">Left: the tree\'s points seen from the side (x against z), wood brown, leaves green. Right: its '
        "cylinder model on the same plane, each cylinder a band as wide as its diameter, coloured by branch order "
        "(stem dark brown).</p>"
        if models
        else '<p class="note">The tree\'s points seen from the side (x against z), '
        + ("wood brown, leaves green" if wood else "grey (wood and leaves not told apart)")
        + "; no cylinder models.</p>"
    )
    out = ["<h2>4. Tree by tree</h2>", note]
    for r in order:
        tid = str(r["tree_id"])
        if tid in drawn:
            out.append(
                f'<figure id="tree-{esc(_file_stem(tid))}">{img_tag(drawn[tid], f"tree {tid}", f"img-tree-{_file_stem(tid)}")}'
                f"<figcaption>Tree {esc(tid)}"
                + (f' &middot; <span class="bad">{esc(r["flag"])}</span>' if r["flag"] else "")
                + "</figcaption></figure>"
            )
    rest = [str(r["tree_id"]) for r in order if str(r["tree_id"]) not in drawn]
    if rest:
        out.append(f"<p>No figure (at most {cap} per report) for trees: {esc(', '.join(rest))}.</p>")
    if problems:
        out.append("<p>Notes:</p><ul>" + "".join(f"<li>{esc(p)}</li>" for p in problems) + "</ul>")
    return "\n".join(out)


def _natural(key: Any) -> tuple:
    return tuple((0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", str(key)) if t)


def _file_stem(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name.strip()) or "tree"


__all__ = ["write_trees_report", "cylinder_polygons", "MAX_TREE_FIGURES"]
