"""Benchmark: cylinder-model wood volume against TreeQSM and against simulated truth.

Rows (forestreg ``measure_trees(..., single_tree=True)``, total and stem volume in m3):

* the shared single trees (``../shared/data``: aRchi Tree_2, AdTree tree1, tree7, Lille_2)
  against the TreeQSM port's figures (:data:`benchmarks.trees_compare.TREEQSM`: PyPI
  ``pytlidar`` 1.1.2, default inputs, run apart in its own environment);
* aRchi's big broadleaf Tree_1 (umr-amap/aRchi @ 6a666764: ``inst/extdata/Tree_1_point_cloud.las``,
  22 m, about 7 cm between points) against the TreeQSM model aRchi ships with it
  (``Tree_1_TreeQSM.txt``: :data:`TREE1_TREEQSM`) and the port; the row is left out unless
  ``aRchi_Tree_1_point_cloud.las`` lies in the shared data folder;
* simulated big broadleaves with known wood (:mod:`forestreg.engine.simulate.wood`: frusta down to
  4 branch orders, ray-cast TLS), one densely sampled with leaves (leaf-wood separation at work)
  and one leaf-off at 0.15 deg from 17 m (6.6 cm between points).

Run from the repository root: ``python -m benchmarks.volume_treeqsm`` (about two minutes).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

if __package__:
    from .trees_compare import DATA, TREEQSM
else:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from trees_compare import DATA, TREEQSM  # type: ignore[no-redef]

#: aRchi's own TreeQSM model of its Tree_1 (MATLAB TreeQSM, cylinders summed: total and branch
#: order 0) and the TreeQSM port on its cloud (pytlidar 1.1.2, default inputs); m3.
TREE1_TREEQSM = {"volume_m3": 3.8991, "stem_volume_m3": 2.0352, "port_volume_m3": 5.3531, "port_stem_volume_m3": 2.1399}

SHARED = ("aRchi_Tree_2_point_cloud.las", "AdTree_tree1.xyz", "AdTree_tree7.xyz", "AdTree_Lille_2.xyz")


def _measure(points: np.ndarray) -> dict[str, float]:
    from forestreg.engine.trees.inventory import measure_trees

    p = points - np.r_[points[:, :2].mean(axis=0), 0.0]
    t = time.perf_counter()
    tree = measure_trees(p, single_tree=True).trees[0]
    m = tree.cylinders
    return {
        "volume_m3": float(m.total_volume_m3) if m is not None else float("nan"),
        "stem_volume_m3": float(m.stem_volume_m3) if m is not None else float("nan"),
        "stem_form_factor": tree.stem_form_factor,
        "flagged": any("volume" in f for f in tree.flags),
        "seconds": time.perf_counter() - t,
    }


def simulated() -> list[tuple[str, np.ndarray, dict[str, float]]]:
    """The simulated broadleaves: (case, points, truth)."""
    from forestreg.engine.simulate.wood import branching_broadleaf, scan_wood_tree

    out = []
    dense = branching_broadleaf(0, dbh_m=0.6, height_m=18.0, crown_radius_m=7.0, orders=4, children_per_m=2.5)
    pts, _ = scan_wood_tree(dense, leaf_area_density=1.0, range_noise_m=0.005, seed=0)
    out.append(
        ("sim broadleaf, dense, leaves", pts, {"volume_m3": dense.volume_m3, "stem_volume_m3": dense.stem_volume_m3})
    )
    sparse = branching_broadleaf(1, dbh_m=0.55, height_m=20.0, crown_radius_m=7.0, orders=4, children_per_m=2.0)
    pts, _ = scan_wood_tree(
        sparse, positions=((-16.0, -6.0), (15.0, -8.0), (3.0, 16.0)), angular_step_deg=0.15, range_noise_m=0.008, seed=1
    )
    out.append(
        ("sim broadleaf, 6.6 cm spacing", pts, {"volume_m3": sparse.volume_m3, "stem_volume_m3": sparse.stem_volume_m3})
    )
    return out


def run() -> list[dict[str, Any]]:
    from forestreg.engine.io import read_scan

    rows: list[dict[str, Any]] = []
    cases: list[tuple[str, Path, dict[str, float]]] = [(n, DATA / n, TREEQSM[n]) for n in SHARED]
    cases.append(("aRchi_Tree_1_point_cloud.las", DATA / "aRchi_Tree_1_point_cloud.las", TREE1_TREEQSM))
    for name, path, ref in cases:
        if not path.exists():
            continue
        got = _measure(np.asarray(read_scan(path).points, dtype=np.float64))
        rows.append(
            {
                "case": name,
                "reference": "TreeQSM",
                **got,
                "ref_volume_m3": ref["volume_m3"],
                "ref_stem_volume_m3": ref["stem_volume_m3"],
            }
        )
    for name, pts, truth in simulated():
        got = _measure(pts)
        rows.append(
            {
                "case": name,
                "reference": "truth",
                **got,
                "ref_volume_m3": truth["volume_m3"],
                "ref_stem_volume_m3": truth["stem_volume_m3"],
            }
        )
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| case | reference | volume m3 (ref) | error | stem m3 (ref) | stem error | stem form factor | flagged |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['reference']} | {r['volume_m3']:.4f} ({r['ref_volume_m3']:.4f}) | "
            f"{100 * (r['volume_m3'] / r['ref_volume_m3'] - 1):+.0f} % | {r['stem_volume_m3']:.4f} ({r['ref_stem_volume_m3']:.4f}) | "
            f"{100 * (r['stem_volume_m3'] / r['ref_stem_volume_m3'] - 1):+.0f} % | {r['stem_form_factor']:.2f} | {'yes' if r['flagged'] else 'no'} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    print(table(run()))
