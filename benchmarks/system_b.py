"""System B benchmarks: ground-based/UAV co-registration, fusion and the tree inventory at full size.

1. Co-registration: a simulated 40 m plot flown by the UAV at 86 m at the paper's density
   (~280 points/m2 on the canopy) and walked with a backpack scanner (the paper's 5-10 thousand
   points/m2) over the central 24 m, misaligned by 180 deg and 10 m; steps from
   ``CoregistrationResult.timings``, errors against the truth.
2. Fusion of the registered pair (redundancy + noise removal), with its counts.
3. Tree inventory of the fused cloud (terrain, stems, segmentation, leaf-wood, cylinders).

Run from the repository root: ``.venv/bin/python benchmarks/run.py`` (both systems) or
``.venv/bin/python -m benchmarks.system_b``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.coreg import coregister
from forestreg.engine.coreg.fusion import fuse_scans
from forestreg.engine.simulate.platforms import simulate_coregistration_case

COREG_STEPS = ("terrain_s", "keypoints_s", "matching_s", "verification_s", "icp_s", "total_s")


def run(seed: int = 0, quick: bool = False) -> list[dict[str, Any]]:
    """Rows: one per co-registration case (with fusion and inventory timings)."""
    rows = []
    cases = [("planted_conifer", "backpack", 180.0, (8.0, -6.0, 1.5))]
    if not quick:
        cases.append(("mixed_temperate", "tls", -75.0, (-4.0, 9.0, -1.0)))
    for preset, platform, heading, offset in cases:
        t = time.perf_counter()
        case = simulate_coregistration_case(
            preset,
            seed=seed,
            size_m=40.0,
            ground_platform=platform,
            heading_deg=heading,
            offset_m=offset,
            uav_density_scale=1.0,
            backpack_density_scale=0.1 if quick else 0.25,
            tls_step_deg=0.2,
        )
        sim_s = time.perf_counter() - t
        result = coregister(case.ground, case.uav)
        row: dict[str, Any] = {
            "case": f"{preset}, {platform}",
            "ground_points": len(case.ground),
            "uav_points": len(case.uav),
            "simulate_s": sim_s,
            "status": result.status,
            "reason": result.reason,
            **{k: result.timings.get(k, float("nan")) for k in COREG_STEPS},
            "keypoints": f"{len(result.ground_keypoints or [])}/{len(result.uav_keypoints or [])}",
            "matched": result.n_matched,
            "matching_percentage": result.matching_percentage,
        }
        if result.ok:
            rot, trans = rigid_errors(result.matrix, case.matrix)
            row.update(rotation_error_deg=rot, translation_error_m=trans)
            t = time.perf_counter()
            fused = fuse_scans(case.ground, case.uav, result.matrix)
            row["fusion_s"] = time.perf_counter() - t
            row["fused_points"] = len(fused)
            row["redundant"] = fused.counts["total"]["redundant"]
            row["noise"] = fused.counts["total"]["noise"]
            if not quick and platform == "tls":  # the tree inventory of the fused TLS + UAV cloud
                from forestreg.engine.trees.inventory import measure_trees

                t = time.perf_counter()
                inventory = measure_trees(fused.points)
                row["trees_s"] = time.perf_counter() - t
                row["trees"] = len(inventory.trees)
        rows.append(row)
    return rows


def format_rows(rows: list[dict[str, Any]]) -> str:
    """A plain-text table of :func:`run`'s rows."""
    cols = [
        ("case", "{}"),
        ("ground_points", "{:,}"),
        ("uav_points", "{:,}"),
        ("status", "{}"),
        ("reason", "{}"),
        ("terrain_s", "{:.1f}"),
        ("keypoints_s", "{:.1f}"),
        ("matching_s", "{:.1f}"),
        ("verification_s", "{:.1f}"),
        ("icp_s", "{:.1f}"),
        ("total_s", "{:.1f}"),
        ("keypoints", "{}"),
        ("matched", "{}"),
        ("matching_percentage", "{:.0f} %"),
        ("rotation_error_deg", "{:.4f}"),
        ("translation_error_m", "{:.4f}"),
        ("fusion_s", "{:.1f}"),
        ("fused_points", "{:,}"),
        ("redundant", "{:,}"),
        ("noise", "{:,}"),
        ("trees_s", "{:.1f}"),
        ("trees", "{}"),
    ]
    lines = ["System B: co-registration (UAV at the paper's density), fusion, tree inventory"]
    width = max(len(c) for c, _ in cols)
    for name, fmt in cols:
        vals = []
        for r in rows:
            v = r.get(name)
            try:
                vals.append("-" if v is None or (isinstance(v, float) and np.isnan(v)) else fmt.format(v))
            except (ValueError, TypeError):
                vals.append(str(v))
        lines.append(f"  {name:<{width}}  " + "  ".join(f"{v:>22}" for v in vals))
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover
    import sys

    quick = "--quick" in sys.argv
    print(format_rows(run(quick=quick)))
