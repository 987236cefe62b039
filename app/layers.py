"""GIS layers beside the tables: ``layers.gpkg`` in the output folder of ``trees``, ``change``,
``plot`` and ``coregister`` (:mod:`forestreg.engine.io.gpkg`, styled for QGIS by
:mod:`forestreg.engine.io.qml`).

Every layer is in the file coordinates of the run's output frame, in the files' unit (the CSVs'
coordinates), with that frame's CRS (:class:`~forestreg.engine.io.crs.FrameCrs`; local, ``srs_id``
-1, when none is known):

* ``trees``: one point per tree at breast height (the stem axis 1.3 m above its base; z that
  height), every column of ``trees.csv``; graduated by DBH, flagged trees ringed in red;
* ``crowns``: each tree's crown outline from above (the convex hull of its crown points,
  :attr:`~forestreg.engine.trees.crown.CrownMeasurement.outline`; an ellipse of the crown widths
  for a tree without one), with its crown figures;
* ``scanners`` and ``links``: a plot's scanner positions and its links as lines between them, with
  each link's status and 1-sigma uncertainty;
* ``tree_changes``: a re-survey's trees with their status and growth, coloured by status;
* ``keypoints``: a co-registration's canopy keypoints in the UAV frame;
* ``next_scans``: where the next scans of a plot should stand (``forestreg plan``, written to
  ``plan.gpkg`` beside ``plan.json``), numbered by rank, with the scan each links to and why;
* ``plot_outline``: the outline of what was measured (the convex hull of the cloud, the scans or
  the trees from above).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional, Sequence

import numpy as np

#: The file name of the layers in an output folder.
LAYERS_FILE = "layers.gpkg"
#: Height of the trees layer's points above the stem base, metres.
BREAST_HEIGHT_M = 1.3

_FLAGGED = '"flag" IS NOT NULL AND "flag" <> \'\''


# ----------------------------------------------------------------------------- shapes


def cloud_outline(xy: np.ndarray) -> Optional[np.ndarray]:
    """The convex hull (M, 2), counter-clockwise, of (N, 2) points ``xy`` (metres) from above; None
    with fewer than 3 points not on one line. The points inside the octagon of the extreme points
    along x, y and the diagonals cannot be hull vertices and are dropped first (Akl-Toussaint):
    a few passes over millions of points leave a few to hull."""
    from ..engine.geometry.hull import extreme_rows, hull_candidates
    from ..engine.trees.crown import convex_hull_2d

    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if not np.isfinite(p.sum()):
        p = p[np.isfinite(p).all(axis=1)]
    if len(p) <= 20_000:
        return convex_hull_2d(p)
    octagon = convex_hull_2d(p[extreme_rows(p)])
    if octagon is None:
        return convex_hull_2d(p)
    # counter-clockwise ring: a point on or right of an edge (cross product <= 0) may be a vertex
    outside = hull_candidates(p, octagon)
    return convex_hull_2d(np.vstack([p[outside], octagon]))


def _ellipse(cx: float, cy: float, a: float, b: float, n: int = 24) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    return np.column_stack([cx + 0.5 * a * np.cos(t), cy + 0.5 * b * np.sin(t)])


def _area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return float(abs(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))


def _finite(v: Any) -> Optional[float]:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


# ----------------------------------------------------------------------------- styles


def _trees_style() -> str:
    from ..engine.io.qml import Rule, marker, rule_style

    classes = [
        (None, 0.10, "DBH < 10 cm", (255, 255, 178, 255), 1.6),
        (0.10, 0.20, "DBH 10-20 cm", (194, 230, 153, 255), 2.2),
        (0.20, 0.30, "DBH 20-30 cm", (120, 198, 121, 255), 2.8),
        (0.30, 0.50, "DBH 30-50 cm", (49, 163, 84, 255), 3.6),
        (0.50, None, "DBH >= 50 cm", (0, 104, 55, 255), 4.4),
    ]
    rules = [Rule("DBH not measured", '"dbh_m" IS NULL', marker((170, 170, 170, 255), 1.4, shape="square"))]
    for lo, hi, label, colour, size in classes:
        parts = ([f'"dbh_m" >= {lo:g}'] if lo is not None else []) + ([f'"dbh_m" < {hi:g}'] if hi is not None else [])
        rules.append(Rule(label, " AND ".join(parts), marker(colour, size)))
    rules.append(
        Rule(
            "flagged (see the flag column)",
            _FLAGGED,
            marker((0, 0, 0, 0), 5.4, outline=(215, 25, 28, 255), outline_mm=0.5),
        )
    )
    return rule_style("trees", "POINT", rules)


def _crowns_style() -> str:
    from ..engine.io.qml import Rule, fill, rule_style

    return rule_style(
        "crowns",
        "POLYGON",
        [
            Rule("crown outline", "", fill((49, 163, 84, 70), (0, 104, 55, 255), 0.3)),
            Rule(
                "flagged tree", _FLAGGED, fill((0, 0, 0, 0), (215, 25, 28, 255), 0.4, outline_style="dash", style="no")
            ),
        ],
    )


def _changes_style() -> str:
    from ..engine.io.qml import Rule, marker, rule_style

    return rule_style(
        "tree_changes",
        "POINT",
        [
            Rule("persisting", "\"status\" = 'persisting'", marker((26, 150, 65, 255), 2.6)),
            Rule("removed", "\"status\" = 'removed'", marker((215, 25, 28, 255), 3.0, shape="cross_fill")),
            Rule("new", "\"status\" = 'new'", marker((43, 131, 186, 255), 2.8, shape="triangle")),
            Rule(
                "outside the other survey", "\"status\" = 'outside'", marker((170, 170, 170, 255), 2.0, shape="square")
            ),
            Rule(
                "flagged (see the flag column)",
                _FLAGGED,
                marker((0, 0, 0, 0), 4.6, outline=(253, 174, 97, 255), outline_mm=0.5),
            ),
        ],
    )


def _scanners_style() -> str:
    from ..engine.io.qml import Rule, marker, rule_style

    return rule_style(
        "scanners",
        "POINT",
        [
            Rule(
                "centre scan (the plot frame)", "\"status\" = 'centre'", marker((255, 215, 0, 255), 4.6, shape="star")
            ),
            Rule("registered", "\"status\" = 'ok'", marker((43, 131, 186, 255), 3.4, shape="triangle")),
            Rule("failed", "\"status\" NOT IN ('ok', 'centre')", marker((215, 25, 28, 255), 3.4, shape="triangle")),
        ],
    )


def _links_style() -> str:
    from ..engine.io.qml import Rule, line, rule_style

    return rule_style(
        "links",
        "LINESTRING",
        [
            Rule("link registered", "\"status\" = 'ok'", line((26, 150, 65, 255), 0.6)),
            Rule("link failed", "\"status\" = 'failed'", line((215, 25, 28, 255), 0.5, style="dash")),
            Rule(
                "link dropped as inconsistent", "\"status\" = 'dropped'", line((150, 150, 150, 255), 0.5, style="dot")
            ),
        ],
    )


def _outline_style() -> str:
    from ..engine.io.qml import Rule, fill, rule_style

    return rule_style(
        "plot_outline", "POLYGON", [Rule("plot outline", "", fill((0, 0, 0, 0), (40, 40, 40, 255), 0.6, style="no"))]
    )


def _next_scans_style() -> str:
    from ..engine.io.qml import Rule, labelled, marker, rule_style

    return labelled(
        rule_style(
            "next_scans",
            "POINT",
            [
                Rule(
                    "next scan 1 (adds the most)",
                    '"rank" = 1',
                    marker((255, 217, 47, 255), 6.0, outline=(0, 0, 0, 255), outline_mm=0.4),
                ),
                Rule(
                    "next scans 2 and 3",
                    '"rank" > 1',
                    marker((255, 247, 188, 255), 5.0, outline=(0, 0, 0, 255), outline_mm=0.4),
                ),
            ],
        ),
        "rank",
        size_pt=10.0,
    )


def _keypoints_style() -> str:
    from ..engine.io.qml import Rule, marker, rule_style

    return rule_style(
        "keypoints",
        "POINT",
        [
            Rule("UAV keypoint", "\"cloud\" = 'uav'", marker((43, 131, 186, 255), 2.4)),
            Rule("ground-based keypoint", "\"cloud\" = 'ground'", marker((253, 174, 97, 255), 2.0, shape="diamond")),
            Rule(
                "matched", '"matched_with" >= 0', marker((0, 0, 0, 0), 3.6, outline=(26, 150, 65, 255), outline_mm=0.4)
            ),
        ],
    )


# ----------------------------------------------------------------------------- layers


def outline_layer(ring: Optional[np.ndarray], name: str, what: str, unit_scale: float = 1.0):
    """The ``plot_outline`` layer: one polygon (``ring``: (M, 2) file coordinates, metres) named
    ``name``, with ``what`` it outlines and its area (m^2); no feature without a ring."""
    from ..engine.io.gpkg import Layer

    rows, shapes = [], []
    if ring is not None and len(ring) >= 3:
        rows.append({"name": name, "outline_of": what, "area_m2": _area(ring)})
        shapes.append(np.asarray(ring, dtype=np.float64) / unit_scale)
    return Layer(
        "plot_outline",
        "POLYGON",
        ("name", "outline_of", "area_m2"),
        rows,
        shapes,
        description=f"outline from above of {what}",
        style=_outline_style(),
        types={"name": "TEXT", "outline_of": "TEXT", "area_m2": "REAL"},
    )


def trees_layers(
    inventory, *, unit_scale: float = 1.0, outline: Optional[np.ndarray] = None, cloud_name: str = "cloud"
) -> list:
    """The ``trees``, ``crowns`` and ``plot_outline`` layers of a tree inventory
    (:class:`~forestreg.engine.trees.inventory.TreeInventory`); ``outline`` the cloud's outline
    from above (local frame, metres), ``unit_scale`` metres per file unit."""
    from ..engine.io.gpkg import Layer
    from ..engine.io.results import TREE_COLUMNS

    shift = np.asarray(inventory.origin_shift, dtype=np.float64)
    rows, points = [], []
    crown_rows, crown_shapes = [], []
    for t, r in zip(inventory.trees, inventory.rows()):
        row = dict(r)
        for k in ("x", "y", "z"):
            row[k] = r[k] / unit_scale
        rows.append(row)
        axis = np.asarray(t.stem.axis, dtype=np.float64)
        up = max(float(axis[2]), 1e-6)
        bh = (
            np.asarray(t.stem.base, dtype=np.float64) + axis * (BREAST_HEIGHT_M / up)
            if np.isfinite(axis).all()
            else np.asarray(t.stem.base, dtype=np.float64) + [0.0, 0.0, BREAST_HEIGHT_M]
        )
        points.append((bh + shift) / unit_scale)
        ring, how = t.crown.outline, "convex hull of the crown points"
        if ring is None or len(ring) < 3:
            a, b = _finite(t.crown.crown_width_ew_m), _finite(t.crown.crown_width_ns_m)
            ring, how = (_ellipse(t.stem.x, t.stem.y, a, b), "ellipse of the crown widths") if a and b else (None, "")
        if ring is None:
            continue
        ring_file = (np.asarray(ring, dtype=np.float64)[:, :2] + shift[:2]) / unit_scale
        crown_rows.append(
            {
                "tree_id": t.tree_id,
                "dbh_m": r.get("dbh_m"),
                "height_m": r.get("height_m"),
                "crown_base_m": r.get("crown_base_m"),
                "crown_width_ew_m": r.get("crown_width_ew_m"),
                "crown_width_ns_m": r.get("crown_width_ns_m"),
                "crown_area_m2": r.get("crown_area_m2"),
                "outline_area_m2": _area(np.asarray(ring)[:, :2]),
                "crown_volume_m3": r.get("crown_volume_m3"),
                "outline": how,
                "flag": r.get("flag", ""),
            }
        )
        crown_shapes.append(ring_file)
    crown_columns = (
        "tree_id",
        "dbh_m",
        "height_m",
        "crown_base_m",
        "crown_width_ew_m",
        "crown_width_ns_m",
        "crown_area_m2",
        "outline_area_m2",
        "crown_volume_m3",
        "outline",
        "flag",
    )
    text = {"height_source", "source", "dbh_quality", "height_quality", "crown_quality", "volume_quality", "flag"}
    layers = [
        Layer(
            "trees",
            "POINT",
            tuple(TREE_COLUMNS),
            rows,
            points,
            z=True,
            style=_trees_style(),
            description="trees at breast height (the stem axis 1.3 m above its base), the columns of trees.csv",
            types={
                c: (
                    "TEXT"
                    if c in text
                    else "INTEGER"
                    if c in ("tree_id", "n_cylinders", "n_branches", "n_points")
                    else "REAL"
                )
                for c in TREE_COLUMNS
            },
        ),
        Layer(
            "crowns",
            "POLYGON",
            crown_columns,
            crown_rows,
            crown_shapes,
            style=_crowns_style(),
            description="crown outlines from above (convex hull of each tree's crown points)",
            types={
                c: ("TEXT" if c in ("outline", "flag") else "INTEGER" if c == "tree_id" else "REAL")
                for c in crown_columns
            },
        ),
    ]
    if outline is not None:
        layers.append(
            outline_layer(np.asarray(outline)[:, :2] + shift[:2], cloud_name, f"the cloud {cloud_name}", unit_scale)
        )
    return layers


def change_layers(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> list:
    """The ``tree_changes`` and ``plot_outline`` layers of a re-survey: ``rows`` the rows of
    ``tree_changes.csv`` (x, y in BEFORE file coordinates, its unit), ``columns`` its columns; the
    outline is the convex hull of every tree of both surveys."""
    from ..engine.io.gpkg import Layer

    cleaned, shapes = [], []
    for r in rows:
        row = {c: (None if r.get(c) == "" else r.get(c)) for c in columns}
        cleaned.append(row)
        shapes.append(np.array([_finite(r.get("x")) or math.nan, _finite(r.get("y")) or math.nan]))
    text = {"status", "flag"}
    ints = {"tree_id_before", "tree_id_after"}
    layer = Layer(
        "tree_changes",
        "POINT",
        tuple(columns),
        cleaned,
        shapes,
        style=_changes_style(),
        description="the trees of both surveys: status (persisting, removed, new, outside), DBH and height growth (m)",
        types={c: ("TEXT" if c in text else "INTEGER" if c in ints else "REAL") for c in columns},
    )
    xy = np.array([s for s in shapes if np.isfinite(s).all()]).reshape(-1, 2)
    from ..engine.trees.crown import convex_hull_2d

    return [layer, outline_layer(convex_hull_2d(xy) if len(xy) >= 3 else None, "trees", "the trees of both surveys")]


def _slices_outline(project, scans) -> tuple[Optional[np.ndarray], str]:
    """The outline from above of what the registered scans measured: the convex hull of their
    stem-height slices in the plot frame (the slices the links were registered on, kept by the
    run: no scan is read again), or (None, "") when they cannot be drawn. A scan's header
    bounds, turned by its pose, cover far more than its points (the box's corners)."""
    from ..engine.report.views import compute_top_view
    from ..engine.trees.crown import convex_hull_2d

    try:
        view = compute_top_view(project, scans)
    except Exception:  # noqa: BLE001 - the layers fall back to the scans' extents
        return None, ""
    xy = [v.slice_xy for v in view.scans.values() if len(v.slice_xy)]
    if not xy or view.problems:
        return None, ""
    return convex_hull_2d(np.vstack(xy)), "the registered scans' stem-height slices"


def plot_layers(project, scans, uncertainty: Mapping[str, Any], outcome=None, *, unit_scale: float = 1.0) -> list:
    """The ``scanners``, ``links`` and ``plot_outline`` layers of a registered plot, in the centre
    scan's file coordinates: each placed scanner (its position moved by its pose), each link as a
    line between its two scanners (NULL geometry where one is not placed) with its status and
    1-sigma uncertainty, and the outline from above of what they measured (:func:`_slices_outline`,
    else the hull of the placed scans' bounds). ``scans`` a
    :class:`~forestreg.engine.tls.plot.ScanCache` (frames and bounds known from the run: nothing
    read again for LAS/LAZ), ``uncertainty`` scan -> 1 sigma."""
    from ..engine.core.transform import apply
    from ..engine.io.gpkg import Layer

    poses = project.poses()
    failed = set() if outcome is None else {n for n, s in outcome.scans.items() if s == "failed"}
    positions: dict[str, np.ndarray] = {}
    scanner_rows, scanner_shapes = [], []
    corners = []
    for s in project.scans:
        pose = None if s.name in failed else poses.get(s.name)
        link = project.link_of(s.name)
        status = "centre" if s.name == project.centre and pose is not None else ("ok" if pose is not None else "failed")
        u = uncertainty.get(s.name) or {}
        row = {
            "scan": s.name,
            "status": status,
            "reference": link.reference if link is not None else None,
            "sigma_translation_m": _finite(u.get("translation_m")),
            "sigma_rotation_deg": _finite(u.get("rotation_deg")),
            "scanner_position": None,
            "file": str(s.path),
        }
        shape = None
        if pose is not None:
            try:
                frame = scans.frame(s.name)
                positions[s.name] = apply(pose, frame.scanner_position_file.reshape(1, 3))[0]
                shape = positions[s.name] / unit_scale
                row["scanner_position"] = str(frame.meta.get("scanner_position", "given"))
                lo, hi = scans.bounds(s.name)
                box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
                corners.append(apply(pose, box)[:, :2])
            except Exception:  # noqa: BLE001 - a scan that cannot be read again: listed without a position
                shape = None
        scanner_rows.append(row)
        scanner_shapes.append(shape)
    dropped = {
        (str(d.get("moving")), str(d.get("reference"))): str(d.get("reason") or "")
        for d in ((project.adjustment or {}).get("dropped") or [])
        if isinstance(d, Mapping)
    }
    link_rows, link_shapes = [], []
    for link in project.links:
        r = link.result
        status = "not run" if r is None else str(r.status)
        reason = "" if r is None else str(r.reason or "")
        if (link.moving, link.reference) in dropped:
            status, reason = "dropped", dropped[(link.moving, link.reference)] or reason
        data = {} if r is None else r
        u = (data.get("uncertainty") or {}) if r is not None else {}
        icp = (data.get("icp") or {}) if r is not None else {}
        link_rows.append(
            {
                "moving": link.moving,
                "reference": link.reference,
                "method": getattr(link, "method", ""),
                "status": status,
                "reason": reason,
                "matched": data.get("matched") if r is not None else None,
                "icp_std_m": _finite(icp.get("std_m")) if isinstance(icp, Mapping) else None,
                "sigma_translation_m": _finite(u.get("translation_m")) if isinstance(u, Mapping) else None,
                "sigma_rotation_deg": _finite(u.get("rotation_deg")) if isinstance(u, Mapping) else None,
            }
        )
        a, b = positions.get(link.moving), positions.get(link.reference)
        link_shapes.append(None if a is None or b is None else np.vstack([a, b]) / unit_scale)
    scanner_cols = (
        "scan",
        "status",
        "reference",
        "sigma_translation_m",
        "sigma_rotation_deg",
        "scanner_position",
        "file",
    )
    link_cols = (
        "moving",
        "reference",
        "method",
        "status",
        "reason",
        "matched",
        "icp_std_m",
        "sigma_translation_m",
        "sigma_rotation_deg",
    )
    from ..engine.trees.crown import convex_hull_2d

    ring, what = _slices_outline(project, scans)
    if ring is None:
        ring, what = (convex_hull_2d(np.vstack(corners)) if corners else None), "the registered scans' extents"
    return [
        Layer(
            "scanners",
            "POINT",
            scanner_cols,
            scanner_rows,
            scanner_shapes,
            z=True,
            style=_scanners_style(),
            description="scanner positions in the plot frame (the centre scan's file coordinates); status centre, ok or failed",
            types={c: ("REAL" if c.startswith("sigma") else "TEXT") for c in scanner_cols},
        ),
        Layer(
            "links",
            "LINESTRING",
            link_cols,
            link_rows,
            link_shapes,
            z=True,
            style=_links_style(),
            description="links (moving scan -> reference scan) with their status and 1-sigma uncertainty",
            types={
                c: ("INTEGER" if c == "matched" else "REAL" if c.startswith(("sigma", "icp")) else "TEXT")
                for c in link_cols
            },
        ),
        outline_layer(ring, project.name or "plot", what, unit_scale),
    ]


def keypoint_layers(
    result, ground, uav, *, ok: bool, unit_scale: float = 1.0, ground_outline: Optional[np.ndarray] = None
) -> list:
    """The ``keypoints`` and ``plot_outline`` layers of a co-registration, in the UAV cloud's file
    coordinates: the UAV keypoints, and when the co-registration succeeded the ground-based ones
    moved by its matrix (metres, file coordinates), each with the keypoint it matched (-1: none);
    the outline is the ground-based cloud's (``ground_outline``, its local frame) moved onto the UAV
    frame. ``ok``: the result passed the last check (its matrix may be used)."""
    from ..engine.core.transform import apply
    from ..engine.io.gpkg import Layer

    ok = ok and getattr(result, "matrix", None) is not None
    pairs = (
        result.matched_after_icp
        if getattr(result, "matched_after_icp", None) is not None
        else (result.match.pairs if getattr(result, "match", None) is not None else np.zeros((0, 2), dtype=int))
    )
    rows, shapes = [], []
    to_uav = None
    if ok:
        to_uav = np.asarray(result.matrix, dtype=np.float64) @ ground.local_to_file_matrix()
    for cloud, kp, column, other, to_file in (
        ("uav", result.uav_keypoints, 1, 0, None if uav is None else uav.local_to_file_matrix()),
        ("ground", result.ground_keypoints, 0, 1, to_uav),
    ):
        if kp is None or to_file is None:
            continue
        matched = np.full(len(kp.xyz), -1)
        if len(pairs):
            matched[np.asarray(pairs)[:, column]] = np.asarray(pairs)[:, other]
        xyz = apply(to_file, np.asarray(kp.xyz, dtype=np.float64)) / unit_scale
        for i, p in enumerate(xyz):
            rows.append(
                {
                    "cloud": cloud,
                    "keypoint_id": i,
                    "cluster_size": int(kp.cluster_sizes[i]),
                    "matched_with": int(matched[i]),
                }
            )
            shapes.append(p)
    ring = None
    if ok and ground_outline is not None:
        ring = apply(to_uav, np.column_stack([ground_outline, np.zeros(len(ground_outline))]))[:, :2]
    cols = ("cloud", "keypoint_id", "cluster_size", "matched_with")
    return [
        Layer(
            "keypoints",
            "POINT",
            cols,
            rows,
            shapes,
            z=True,
            style=_keypoints_style(),
            description="canopy keypoints in the UAV frame (ground-based ones moved by the co-registration)",
            types={"cloud": "TEXT", "keypoint_id": "INTEGER", "cluster_size": "INTEGER", "matched_with": "INTEGER"},
        ),
        outline_layer(
            ring, getattr(ground, "name", "ground") or "ground", "the ground-based cloud in the UAV frame", unit_scale
        ),
    ]


#: Columns of the ``next_scans`` layer.
NEXT_SCAN_COLUMNS = (
    "rank",
    "links_to",
    "shared_stems",
    "needed",
    "vop_radius_m",
    "distance_m",
    "new_stem_area_m2",
    "new_view_m2",
    "expected_stem_area_m2",
    "reason",
)


def plan_layers(plan, *, unit_scale: float = 1.0) -> list:
    """The ``next_scans`` layer of a plan (:class:`~forestreg.engine.tls.plan.ScanPlan`): one point
    per suggestion at its position (plan frame: the centre scan's file coordinates, metres over
    ``unit_scale`` metres per file unit), best first, with its rank (1-3), the placed scan it links
    to, the trunk shadows they are expected to share (``needed`` at least) at D_r
    ``vop_radius_m``, its distance to that scanner (m), the stem area no placed scan saw that it
    would see (m2), the plot area hidden so far that it has in view (m2) and the stem area expected
    there (m2), and the reason in words. No feature when no position links."""
    from ..engine.io.gpkg import Layer

    rows, shapes = [], []
    for k, s in enumerate(plan.suggestions, 1):
        rows.append(
            {
                "rank": k,
                "links_to": s.links_to,
                "shared_stems": int(s.shared_stems),
                "needed": int(s.needed),
                "vop_radius_m": float(s.radius_m),
                "distance_m": float(s.distance_m),
                "new_stem_area_m2": float(s.new_stem_area_m2),
                "new_view_m2": float(s.new_view_m2),
                "expected_stem_area_m2": float(s.expected_stem_area_m2),
                "reason": s.reason,
            }
        )
        shapes.append(np.array([s.x, s.y], dtype=np.float64) / unit_scale)
    ints, text = {"rank", "shared_stems", "needed"}, {"links_to", "reason"}
    return [
        Layer(
            "next_scans",
            "POINT",
            NEXT_SCAN_COLUMNS,
            rows,
            shapes,
            style=_next_scans_style(),
            description="where to scan next (forestreg plan): each suggested scanner position by rank, the placed scan it links "
            "to, the trunk shadows expected shared and the stem area it would newly see",
            types={c: ("INTEGER" if c in ints else "TEXT" if c in text else "REAL") for c in NEXT_SCAN_COLUMNS},
        )
    ]


def write_layers(folder, layers: Iterable, crs=None) -> Path:
    """Write ``layers`` into ``folder/layers.gpkg`` with ``crs`` (a
    :class:`~forestreg.engine.io.crs.Crs`, None: local coordinates); returns its path."""
    from ..engine.io.gpkg import write_geopackage

    return write_geopackage(Path(folder) / LAYERS_FILE, list(layers), crs)
