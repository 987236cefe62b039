"""Figures of a pair registration (matplotlib, no display needed).

Top views in the reference scan's levelled scanner frame (metres): each scan's slice with its
visual occlusion points, and both after registration with the matched VOP pairs joined.
"""

from __future__ import annotations

import os
import textwrap
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..core.atomic import atomic_path  # noqa: E402
from ..core.errors import InvalidArgumentError  # noqa: E402
from .raster import add_points  # noqa: E402

if TYPE_CHECKING:  # pragma: no cover
    from ..tls.pair import PairResult

from ..tls.views import MOVING_COLOUR, REFERENCE_COLOUR  # noqa: E402,F401 - one definition of the scan colours


#: PNG settings of the figures: zlib's fastest level (flat colours and dots compress well at any
#: level; the default level 6 took ~3x as long for a file a fifth smaller)
FAST_PNG = {"compress_level": 1}


def _slice_points(layers, radius: float, limit: int = 60000) -> np.ndarray:
    pts = np.concatenate([layer.xyz for layer in layers]) if layers else np.zeros((0, 3))
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) <= radius + 5.0]
    if len(pts) > limit:
        pts = pts[:: len(pts) // limit + 1]
    return pts


def _apply2(matrix: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ matrix[:2, :2].T + matrix[:2, 3]


def pair_figure(result: "PairResult", path: str | os.PathLike[str], *, dpi: int = 110) -> None:
    """Write a PNG with three top views: the reference slice and VOPs, the moving slice and VOPs,
    and both overlaid with the final (or, if failed, the best coarse) transform and matched pairs."""
    det = result.details
    if det is None or det.chosen is None:
        raise InvalidArgumentError("the result carries no details to draw")
    att = det.chosen
    radius = att.radius_m
    fig, axes = plt.subplots(1, 3, figsize=(18, 6.2))
    for ax, layers, vops, colour, title in (
        (axes[0], det.reference_layers, att.reference_vops, REFERENCE_COLOUR, f"reference {result.reference_name}"),
        (axes[1], det.moving_layers, att.moving_vops, MOVING_COLOUR, f"moving {result.moving_name}"),
    ):
        pts = _slice_points(layers, radius)
        add_points(ax, [(pts[:, :2], "0.45", 2.0)])  # opaque dots: a little larger than the antialiased s=1 scatter was
        if len(vops.rejected_xy):
            ax.scatter(vops.rejected_xy[:, 0], vops.rejected_xy[:, 1], marker="x", s=14, c="0.35", linewidths=0.8, label="rejected (visibility)")
        ax.scatter(vops.xy[:, 0], vops.xy[:, 1], s=28, facecolors="none", edgecolors=colour, linewidths=1.4, label=f"{len(vops)} VOPs")
        ax.add_patch(plt.Circle((0, 0), radius, fill=False, ls="--", color="0.3", lw=0.8))
        ax.plot(0, 0, marker="^", color="k", ms=9)
        ax.set_title(f"{title}: slice and VOPs (D_r {radius:.0f} m)")
        ax.legend(loc="upper right", fontsize=8)
    ax = axes[2]
    matrix = det.lsf_matrix if det.lsf_matrix is not None else det.coarse_lsf_matrix
    ref_pts = _slice_points(det.reference_layers, radius)
    add_points(ax, [(ref_pts[:, :2], "#6baed6", 2.0)])
    if matrix is not None:
        mov_pts = _slice_points(det.moving_layers, radius)
        moved = _apply2(matrix, mov_pts[:, :2])
        add_points(ax, [(moved, "#fd8d3c", 2.0)])
        mov_vops = _apply2(matrix, att.moving_vops.xy)
        ax.plot(matrix[0, 3], matrix[1, 3], marker="^", color=MOVING_COLOUR, ms=9)
    else:
        mov_vops = np.zeros((0, 2))
    ax.scatter(att.reference_vops.xy[:, 0], att.reference_vops.xy[:, 1], s=28, facecolors="none", edgecolors=REFERENCE_COLOUR, linewidths=1.4, label="reference VOPs")
    if len(mov_vops):
        ax.scatter(mov_vops[:, 0], mov_vops[:, 1], s=14, c=MOVING_COLOUR, marker="+", linewidths=1.2, label="moving VOPs")
    if att.match is not None and len(mov_vops) and len(att.match.matched_pairs):
        from matplotlib.collections import LineCollection

        pairs = np.asarray(att.match.matched_pairs, dtype=np.int64).reshape(-1, 2)
        a, b = att.reference_vops.xy[pairs[:, 0]], mov_vops[pairs[:, 1]]
        ax.add_collection(LineCollection(np.stack([a, b], axis=1), colors="#2ca02c", linewidths=2.2))
        ax.scatter(a[:, 0], a[:, 1], s=81, facecolors="none", edgecolors="#2ca02c", linewidths=1.6)
    ax.plot(0, 0, marker="^", color=REFERENCE_COLOUR, ms=9)
    title = f"registered: {result.matched} matched VOPs (green) - " + ("ok" if result.ok else f"FAILED: {result.reason}")
    ax.set_title(textwrap.fill(title, 62, max_lines=2, placeholder=" ..."), multialignment="center")  # within its panel
    ax.legend(loc="upper right", fontsize=8)
    for ax in axes:
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.grid(True, lw=0.3)
    # fixed margins for this fixed layout (three equal-aspect panels): ``tight_layout`` measured
    # every tick label and title for ~0.13 s of a 0.33 s figure
    fig.subplots_adjust(left=0.04, right=0.99, bottom=0.08, top=0.94 if "\n" not in ax.get_title() else 0.9, wspace=0.14)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", pil_kwargs=FAST_PNG)
    plt.close(fig)
