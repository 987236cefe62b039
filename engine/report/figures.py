"""The figure of a pair registration, drawn with Pillow (:mod:`.topview`; no display, no
matplotlib: the figure of every ``forestreg register`` run).

Top views in each scan's levelled scanner frame (metres): each scan's slice with its visual
occlusion points, and both after registration (in the reference's frame) with the matched VOP
pairs joined.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np

from ..core.atomic import atomic_path
from ..core.errors import InvalidArgumentError
from .topview import Canvas, Panel

if TYPE_CHECKING:  # pragma: no cover
    from ..tls.pair import PairResult

from .topview import MOVING_COLOUR, REFERENCE_COLOUR  # noqa: E402,F401 - one definition of the scan colours

#: Characters of a panel's title line: a longer title (a long scan name, a failure's reason) is
#: wrapped on two lines, and the panels start lower.
TITLE_WIDTH = 62


def _slice_points(layers, radius: float, limit: int = 60000) -> np.ndarray:
    pts = np.concatenate([layer.xyz for layer in layers]) if layers else np.zeros((0, 3))
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) <= radius + 5.0]
    if len(pts) > limit:
        pts = pts[:: len(pts) // limit + 1]
    return pts


def _apply2(matrix: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ matrix[:2, :2].T + matrix[:2, 3]


def _extent(*clouds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corner (x, y) of the clouds' finite points ((N, 2) each); a 1 m square
    without any (a failed result's matrix may hold NaN)."""
    xy = np.concatenate([np.asarray(c, dtype=float).reshape(-1, 2) for c in clouds]) if clouds else np.zeros((0, 2))
    xy = xy[np.isfinite(xy).all(axis=1)]
    if not len(xy):
        return np.array([-0.5, -0.5]), np.array([0.5, 0.5])
    return xy.min(axis=0), xy.max(axis=0)


def _boxes(two_line_title: bool) -> list[tuple[float, float, float, float]]:
    """The three panels' boxes (left, top, right, bottom; fractions of the figure, top down)."""
    left, right, bottom, top = 0.04, 0.99, 0.92, 0.10 if two_line_title else 0.06
    width = (right - left) / (3 + 2 * 0.14)
    return [(left + k * width * 1.14, top, left + k * width * 1.14 + width, bottom) for k in range(3)]


def pair_figure(result: "PairResult", path: str | os.PathLike[str], *, dpi: int = 110) -> None:
    """Write a PNG (18 x 6.2 inches at ``dpi``) with three top views: the reference slice and
    VOPs, the moving slice and VOPs, and both overlaid with the final (or, if failed, the best
    coarse) transform and the matched pairs."""
    canvas, _ = draw_pair(result, dpi=dpi)
    with atomic_path(path) as tmp:
        canvas.save(tmp)


def _uncertainty_line(result: "PairResult") -> str:
    """The stated 1-sigma uncertainty of an ok result and, in a few words, what it counted (weak
    motions, the alternatives; the full texts are in ``result.json``), for the registered panel's
    title; "" for a failed one (its reason says it)."""
    u = result.uncertainty or {}
    if not result.ok or u.get("translation_m") is None:
        return ""
    line = f"; 1 sigma {100 * u['translation_m']:.1f} cm / {u['rotation_deg']:.3f} deg"
    for w in u.get("weak_directions") or ():
        if w.get("kind") == "translation" and w.get("azimuth_deg") is not None:
            line += f"; free along {w['azimuth_deg']:.0f} deg"
        elif w.get("kind") == "rotation":
            line += "; heading weakly pinned"
    alternatives = [a for a in u.get("alternatives") or () if isinstance(a, dict)]
    counted = [a for a in alternatives if a.get("status") == "counted"]
    if counted:
        line += "; alternative " + ", ".join(f"{a['offset_m']:.2f} m" for a in counted) + " counted"
    elif alternatives:
        line += f"; {len(alternatives)} alternative{'s' if len(alternatives) > 1 else ''} excluded"
    return line


def draw_pair(result: "PairResult", *, dpi: int = 110) -> tuple[Canvas, list[Panel]]:
    """The pair figure drawn (:func:`pair_figure`), not written: its canvas and its three
    panels."""
    det = result.details
    if det is None or det.chosen is None:
        raise InvalidArgumentError("the result carries no details to draw")
    att = det.chosen
    radius = att.radius_m
    matrix = det.lsf_matrix if det.lsf_matrix is not None else det.coarse_lsf_matrix
    within = f"(D_r\u00a0{radius:.0f}\u00a0m)"  # no-break spaces: wrapped as one word
    titles = [
        f"reference {result.reference_name}: slice and VOPs {within}",
        f"moving {result.moving_name}: slice and VOPs {within}",
        f"registered: {result.matched} matched VOPs (green) - "
        + ("ok" if result.ok else f"FAILED: {result.reason}")
        + _uncertainty_line(result),
    ]
    canvas = Canvas(18.0, 6.2, dpi)
    boxes = _boxes(any(len(t) > TITLE_WIDTH for t in titles))  # room for titles on two lines
    sides = []
    for box, layers, vops in (
        (boxes[0], det.reference_layers, att.reference_vops),
        (boxes[1], det.moving_layers, att.moving_vops),
    ):
        pts = _slice_points(layers, radius)[:, :2]
        circle = np.array([[-radius, -radius], [radius, radius]])
        panel = Panel(canvas, box, *_extent(pts, vops.xy, vops.rejected_xy, circle))
        panel.points(pts, "0.45", 2.0)
        sides.append(panel)
    ref_pts = _slice_points(det.reference_layers, radius)[:, :2]
    moved = _apply2(matrix, _slice_points(det.moving_layers, radius)[:, :2]) if matrix is not None else np.zeros((0, 2))
    mov_vops = _apply2(matrix, att.moving_vops.xy) if matrix is not None else np.zeros((0, 2))
    scanner = matrix[:2, 3][None, :] if matrix is not None else np.zeros((0, 2))
    joint = Panel(canvas, boxes[2], *_extent(ref_pts, moved, att.reference_vops.xy, mov_vops, scanner))
    joint.points(ref_pts, "#6baed6", 2.0)
    joint.points(moved, "#fd8d3c", 2.0)
    for panel, vops, colour, title in (
        (sides[0], att.reference_vops, REFERENCE_COLOUR, titles[0]),
        (sides[1], att.moving_vops, MOVING_COLOUR, titles[1]),
    ):
        panel.frame(title, wrap=TITLE_WIDTH)
        if len(vops.rejected_xy):
            panel.markers(vops.rejected_xy, "x", "0.35", size=14, line_pt=0.8, label="rejected (visibility)")
        panel.markers(vops.xy, "o", colour, size=28, line_pt=1.4, label=f"{len(vops)} VOPs")
        panel.dashed_circle((0.0, 0.0), radius, "0.3", line_pt=0.8)
        panel.markers(np.zeros((1, 2)), "^", "#000000", size=81)
        panel.legend()
    joint.frame(titles[2], wrap=TITLE_WIDTH)
    if len(scanner):
        joint.markers(scanner, "^", MOVING_COLOUR, size=81)
    joint.markers(att.reference_vops.xy, "o", REFERENCE_COLOUR, size=28, line_pt=1.4, label="reference VOPs")
    if len(mov_vops):
        joint.markers(mov_vops, "+", MOVING_COLOUR, size=14, line_pt=1.2, label="moving VOPs")
    if att.match is not None and len(mov_vops) and len(att.match.matched_pairs):
        pairs = np.asarray(att.match.matched_pairs, dtype=np.int64).reshape(-1, 2)
        a, b = att.reference_vops.xy[pairs[:, 0]], mov_vops[pairs[:, 1]]
        joint.segments(a, b, "#2ca02c", line_pt=2.2)
        joint.markers(a, "o", "#2ca02c", size=81, line_pt=1.6)
    joint.markers(np.zeros((1, 2)), "^", REFERENCE_COLOUR, size=81)
    joint.legend()
    return canvas, [*sides, joint]
