"""Pictures of a ground-based / UAV co-registration: keypoints before and after, matched pairs,
a side profile of both clouds after registration, and an HTML page with the figures and numbers.

All views are in the UAV cloud's local frame (metres); the ground-based cloud is drawn where the
result puts it (or, before registration, in its own frame).
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..core.atomic import atomic_path, write_text_atomic  # noqa: E402
from ..core.transform import apply as apply_transform
from .samples import profile_sample

if TYPE_CHECKING:  # pragma: no cover
    from ..coreg.coregister import CoregistrationResult

GROUND_COLOUR = "#d62728"
UAV_COLOUR = "#1f77b4"

__all__ = ["coregistration_png", "write_coregistration_report"]


def coregistration_png(
    result: "CoregistrationResult",
    ground_points: Optional[np.ndarray] = None,
    uav_points: Optional[np.ndarray] = None,
    *,
    dpi: int = 100,
) -> bytes:
    """PNG bytes: (1) keypoints before registration, (2) after, with matched pairs joined,
    (3) a side profile of both clouds (local frames) after registration when they are given."""
    g_kp = result.ground_keypoints
    u_kp = result.uav_keypoints
    matrix = result.local_matrix if result.local_matrix is not None else result.keypoint_matrix
    panels = 3 if ground_points is not None and uav_points is not None and matrix is not None else 2
    fig, axes = plt.subplots(1, panels, figsize=(6.4 * panels, 6.2))
    ax0, ax1 = axes[0], axes[1]
    for ax, moved, title in (
        (ax0, None, "before: each cloud in its own frame"),
        (ax1, matrix, "after: ground-based keypoints moved onto the UAV frame"),
    ):
        if u_kp is not None and len(u_kp):
            ax.scatter(u_kp.canopy[::7, 0], u_kp.canopy[::7, 1], s=0.4, c="#9ecae1", linewidths=0)
            ax.scatter(
                u_kp.xyz[:, 0], u_kp.xyz[:, 1], marker="x", s=36, c=UAV_COLOUR, label=f"UAV keypoints ({len(u_kp)})"
            )
        if g_kp is not None and len(g_kp):
            kp = g_kp.xyz if moved is None else apply_transform(moved, g_kp.xyz)
            ax.scatter(
                kp[:, 0],
                kp[:, 1],
                s=40,
                facecolors="none",
                edgecolors=GROUND_COLOUR,
                linewidths=1.4,
                label=f"ground-based keypoints ({len(g_kp)})",
            )
            pairs = None
            if moved is not None:
                pairs = (
                    result.matched_after_icp
                    if result.matched_after_icp is not None
                    else (result.match.pairs if result.match is not None else None)
                )
            if pairs is not None and u_kp is not None:
                for gi, ui in pairs:
                    ax.plot([kp[gi, 0], u_kp.xyz[ui, 0]], [kp[gi, 1], u_kp.xyz[ui, 1]], c="k", lw=1.2)
                ax.plot([], [], c="k", lw=1.2, label=f"matched ({len(pairs)})")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(title, fontsize=10)
        if ax.get_legend_handles_labels()[1]:
            ax.legend(loc="upper right", fontsize=8)
    if panels == 3 and matrix is not None:
        ax = axes[2]
        g = apply_transform(matrix, profile_sample(ground_points, "ground"))
        u = profile_sample(uav_points, "uav")
        centre = np.median(g[:, 1])
        gs = g[np.abs(g[:, 1] - centre) < 1.0]
        us = u[np.abs(u[:, 1] - centre) < 1.0]
        ax.scatter(us[:, 0], us[:, 2], s=0.6, c=UAV_COLOUR, linewidths=0, label="UAV")
        ax.scatter(gs[:, 0], gs[:, 2], s=0.3, c=GROUND_COLOUR, linewidths=0, alpha=0.6, label="ground-based")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
        ax.set_title(f"profile y = {centre:.1f} +- 1 m after registration", fontsize=10)
        ax.legend(loc="upper right", fontsize=8, markerscale=8)
    status = "OK" if result.ok else f"FAILED: {result.reason}"
    fig.suptitle(
        f"{result.ground_name} -> {result.uav_name}: {status}\n{result.n_matched} keypoints matched "
        f"({result.matching_percentage:.0f} %)",
        fontsize=11,
    )
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return buf.getvalue()


def write_coregistration_report(
    result: "CoregistrationResult",
    out_dir: str | os.PathLike[str],
    ground_points: Optional[np.ndarray] = None,
    uav_points: Optional[np.ndarray] = None,
) -> Path:
    """Write ``coregistration.png`` and a self-contained ``report.html`` into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    png = coregistration_png(result, ground_points, uav_points)
    with atomic_path(out / "coregistration.png") as tmp:
        Path(tmp).write_bytes(png)
    d = result.to_dict()
    rows = [
        ("status", d["status"] + (f" ({d['reason']})" if d["reason"] else "")),
        ("keypoints ground-based / UAV", f"{d['keypoints']['ground']} / {d['keypoints']['uav']}"),
        ("matched keypoints", f"{d['matched']} ({d['matching_percentage']:.1f} %)"),
    ]
    for key, label in (
        ("residuals_m", "keypoint residual before ICP"),
        ("residuals_after_icp_m", "keypoint residual after ICP"),
    ):
        r = d[key]
        if r["mean"] == r["mean"]:  # not NaN
            rows.append(
                (
                    label,
                    f"mean {100 * r['mean']:.1f} cm, median {100 * r['median']:.1f} cm, "
                    f"quartiles {100 * r['q1']:.1f} - {100 * r['q3']:.1f} cm",
                )
            )
    if d["icp"]:
        rows.append(
            (
                "ICP",
                f"fitness {d['icp']['fitness']:.2f}, RMSE {100 * d['icp']['rmse_m']:.1f} cm, "
                f"std {100 * d['icp']['std_m']:.1f} cm",
            )
        )
    rows.append(
        (
            "canopy surface correlation (result / best distinct alternative, margin)",
            f"{d['surface_correlation']:.2f} / {d['alternative_correlation']:.2f} (margin {d['correlation_margin']:.2f}, "
            f"{d['candidates_verified']} candidates refined and verified)",
        )
    )
    se = d.get("standard_errors")
    if se:
        rows.append(
            (
                "standard errors (jackknife over plot quadrants)",
                f"rotation {se['rotation_deg']:.3f} deg (heading {se['heading_deg']:.3f}, tilt {se['tilt_deg']:.3f}), "
                f"translation {100 * se['translation_m']:.1f} cm (horizontal {100 * se['horizontal_m']:.1f}, "
                f"vertical {100 * se['vertical_m']:.1f})",
            )
        )
    q = d.get("quality")
    if q:
        if q.get("ground_dz_count") and q.get("ground_dz_median_m") is not None:
            rows.append(
                (
                    "ground height agreement (UAV ground - ground-based DEM)",
                    f"median {100 * q['ground_dz_median_m']:+.1f} cm, NMAD {100 * q['ground_dz_nmad_m']:.1f} cm "
                    f"({q['ground_dz_count']} points)",
                )
            )
        if q.get("canopy_dz_count") and q.get("canopy_dz_median_m") is not None:
            rows.append(
                (
                    "canopy surface residual (UAV top - ground-based top, 1 m cells)",
                    f"median {100 * q['canopy_dz_median_m']:+.1f} cm, NMAD {100 * q['canopy_dz_nmad_m']:.1f} cm "
                    f"({q['canopy_dz_count']} cells)",
                )
            )
    if d["heading_deg"] is not None:
        rows.append(("heading", f"{d['heading_deg']:.3f} deg"))
    table = "\n".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(str(v))}</td></tr>" for k, v in rows)
    matrix = (
        ""
        if d["matrix"] is None
        else "<pre>" + "\n".join(" ".join(f"{v: .9f}" for v in row) for row in d["matrix"]) + "</pre>"
    )
    page = f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>forestreg co-registration</title>
<style>body{{font-family:sans-serif;margin:1.5em;max-width:1400px}} th{{text-align:left;padding-right:1em}}
img{{max-width:100%}} pre{{background:#f4f4f4;padding:.5em}}</style></head><body>
<h1>Ground-based / UAV co-registration</h1>
<p>{html.escape(d["ground"])} &rarr; {html.escape(d["uav"])}; {html.escape(d["convention"])}</p>
<table>{table}</table>
<h2>Matrix</h2>{matrix}
<h2>Keypoints and profile</h2>
<img src="data:image/png;base64,{base64.b64encode(png).decode()}" alt="keypoints before and after">
<h2>Timings (s)</h2><pre>{html.escape(json.dumps(d["timings"], indent=1))}</pre>
</body></html>
"""
    path = out / "report.html"
    write_text_atomic(path, page)
    return path
