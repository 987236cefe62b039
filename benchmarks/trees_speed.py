"""Benchmark: speed of the tree inventory (``measure_trees``) on a plot of System B's size, with
its accuracy against the simulator's truth in the same run.

The case: a simulated ``mixed_temperate`` plot (26 m square, about 59 trees), scanned by TLS
from five positions at 0.19 deg: about 2.9 M points, the size of System B's fused TLS + UAV
cloud (2.9 M points, 57 trees). The merged cloud and the true trees are cached under
``bench_out/trees_speed/`` (``plot.laz``, ``truth.json``) and simulated again only when missing.

Printed: the per-step timings of ``TreeInventory.timings`` (``*_s``, seconds) and the total, and
the accuracy: true trees (DBH >= 0.1 m, inside the plot less 1 m) found within 0.3 m, false
stems, DBH rRMSE, median height error of the trees whose top was scanned, median crown-width
error, and the summed cylinder-model volume. ``--save NAME`` also writes the per-tree figures to
``bench_out/trees_speed/NAME.json``, ``--compare NAME`` counts the trees whose figures differ from
that saved run (two versions compared tree by tree), ``--profile`` writes cProfile statistics to
``bench_out/trees_speed/profile.pstats`` and prints the top entries. The process CPU time (all
threads) is printed beside the wall time: on a busy machine it is the steadier of the two.

Run from the repository root: ``python -m benchmarks.trees_speed [--save NAME] [--compare NAME] [--profile]``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

OUT = Path("bench_out") / "trees_speed"
PRESET, SEED, SIZE_M, STEP_DEG = "mixed_temperate", 3, 26.0, 0.19
POSITIONS = [(-6.0, -6.0), (6.0, -6.0), (0.0, 6.0), (0.0, 0.0), (-6.0, 6.0)]


def load_case(out: Path = OUT) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """The merged cloud ((N, 3) float64, scene frame, metres) and the true trees (dicts with
    ``x, y, z, dbh_m, height_m, crown_radius_m, top_seen``); simulated and cached when missing."""
    from forestreg.engine.io import read_scan, write_points

    laz, truth_path = out / "plot.laz", out / "truth.json"
    if laz.exists() and truth_path.exists():
        return read_scan(laz).points, json.loads(truth_path.read_text())
    from scipy.spatial import cKDTree

    from forestreg.engine.simulate import simulate_plot

    plot = simulate_plot(PRESET, POSITIONS, seed=SEED, angular_step_deg=STEP_DEG, size_m=SIZE_M)
    points = np.vstack([s.world_points() for s in plot.scans])
    obj = np.concatenate([s.object_ids for s in plot.scans])
    trees = []
    for t in plot.scene.trees:
        mine = points[obj == t.id]
        top = t.point_at_height(t.height_m)
        seen = len(mine) > 0 and float(cKDTree(mine).query(top)[0]) < 0.3
        trees.append(
            {
                "id": t.id,
                "x": t.x,
                "y": t.y,
                "z": t.z,
                "dbh_m": t.dbh_m,
                "height_m": t.height_m,
                "crown_radius_m": t.crown_radius_m,
                "top_seen": bool(seen),
            }
        )
    out.mkdir(parents=True, exist_ok=True)
    write_points(laz, points)
    truth_path.write_text(json.dumps({"trees": trees, "n_points": len(points)}, indent=1))
    return read_scan(laz).points, json.loads(truth_path.read_text())  # as the file stores them (mm)


def accuracy(inventory: Any, truth: dict[str, Any]) -> dict[str, float]:
    """Figures of the inventory against the true trees (see the module docstring)."""
    trees = truth["trees"]
    half = 0.5 * SIZE_M - 1.0
    txy = np.array([(t["x"], t["y"]) for t in trees])
    pairs = []
    for rec in inventory.trees:
        d = np.hypot(txy[:, 0] - rec.stem.x, txy[:, 1] - rec.stem.y)
        k = int(np.argmin(d))
        if d[k] < 0.3:
            pairs.append((rec, trees[k]))
    found = {t["id"] for _, t in pairs}
    inside = [t for t in trees if abs(t["x"]) < half and abs(t["y"]) < half and t["dbh_m"] >= 0.1]
    dbh = np.array([(r.dbh_m, t["dbh_m"]) for r, t in pairs if math.isfinite(r.dbh_m)])
    h = [
        abs(r.crown.height_m - t["height_m"]) / t["height_m"]
        for r, t in pairs
        if t["top_seen"] and math.isfinite(r.crown.height_m)
    ]
    w = [
        abs(0.5 * (r.crown.crown_width_ew_m + r.crown.crown_width_ns_m) - 2 * t["crown_radius_m"])
        / (2 * t["crown_radius_m"])
        for r, t in pairs
        if t["top_seen"] and r.crown.ok
    ]
    return {
        "trees": len(inventory.trees),
        "found": sum(t["id"] in found for t in inside),
        "true": len(inside),
        "false_stems": len(inventory.trees) - len(pairs),
        "dbh_measured": len(dbh),
        "dbh_rrmse_pct": 100 * math.sqrt(np.mean((dbh[:, 0] - dbh[:, 1]) ** 2)) / dbh[:, 1].mean()
        if len(dbh)
        else math.nan,
        "height_err_median_pct": 100 * float(np.median(h)) if h else math.nan,
        "crown_width_err_median_pct": 100 * float(np.median(w)) if w else math.nan,
        "volume_sum_m3": float(np.nansum([r.volume_m3 for r in inventory.trees])),
        "wood_fraction": float(np.mean(inventory.wood_probability >= 0.5)),
    }


def per_tree(inventory: Any) -> list[dict[str, Any]]:
    """Each tree's position and main figures (to compare two versions tree by tree)."""
    return [
        {
            k: r[k]
            for k in (
                "tree_id",
                "x",
                "y",
                "dbh_m",
                "height_m",
                "crown_width_ew_m",
                "crown_width_ns_m",
                "crown_volume_m3",
                "volume_m3",
                "n_cylinders",
                "n_points",
                "wood_fraction",
                "flag",
            )
        }
        for r in inventory.rows()
    ]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--save", help="write the per-tree figures to bench_out/trees_speed/NAME.json")
    ap.add_argument("--compare", help="count the trees differing from bench_out/trees_speed/NAME.json")
    ap.add_argument("--profile", action="store_true", help="profile measure_trees with cProfile")
    args = ap.parse_args(argv)
    from forestreg.engine.trees.inventory import measure_trees

    points, truth = load_case()
    print(f"{len(points):,} points, {len(truth['trees'])} true trees")
    if args.profile:
        import cProfile
        import pstats

        prof = cProfile.Profile()
        cpu, t = time.process_time(), time.perf_counter()
        inventory = prof.runcall(measure_trees, points)
        total, cpu = time.perf_counter() - t, time.process_time() - cpu
        prof.dump_stats(str(OUT / "profile.pstats"))
        pstats.Stats(prof).sort_stats("cumulative").print_stats(45)
    else:
        cpu, t = time.process_time(), time.perf_counter()
        inventory = measure_trees(points)
        total, cpu = time.perf_counter() - t, time.process_time() - cpu
    print(
        "timings (s): "
        + "  ".join(f"{k} {v:.1f}" for k, v in inventory.timings.items())
        + f"  total {total:.1f}  (cpu {cpu:.1f})"
    )
    acc = accuracy(inventory, truth)
    print("accuracy: " + "  ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in acc.items()))
    trees = per_tree(inventory)
    if args.compare:
        saved = json.loads((OUT / f"{args.compare}.json").read_text())["trees"]
        differ = sum(json.dumps(a) != json.dumps(b) for a, b in zip(saved, trees)) + abs(len(saved) - len(trees))
        print(f"compared with {args.compare}: {differ} of {len(trees)} trees differ")
    if args.save:
        (OUT / f"{args.save}.json").write_text(
            json.dumps(
                {"timings": {**inventory.timings, "total_s": total, "cpu_s": cpu}, "accuracy": acc, "trees": trees},
                indent=1,
            )
        )


if __name__ == "__main__":  # pragma: no cover
    main()
