"""Benchmark: forestreg's own numerics against the libraries that do the same job, in one process.

Three parts, each printed as a table:

* ``icp``: forestreg's coarse-to-fine point-to-plane ICP (:func:`forestreg.engine.geometry.icp.icp`,
  the pair registration's :class:`~forestreg.engine.geometry.icp_params.IcpParams`) against Open3D's
  ``registration_icp`` with ``TransformationEstimationPointToPlane`` and a robust kernel (Tukey and
  Huber, scale = the stage's correspondence distance), run with the same stages (0.5, 0.2, 0.08 m;
  each cloud thinned to max(0.05 m, distance / 2.5); 12-neighbour normals; at most 40 iterations a
  stage; the same random subset of at most 30 000 moving points a stage as forestreg uses).
  Cases: two simulated TLS scans with their true relative pose
  (:func:`~forestreg.engine.simulate.plot.simulate_plot`), and a real pair: two overlapping crops
  of ``LPine1_demo.laz`` (different random quarters of its points, the second moved by a known
  rigid motion). Every run starts from the truth disturbed by 0.3 m and 2 degrees. Each method
  runs twice (forestreg after a warm-up run that loads its compiled kernels): the time of each run (wall, seconds), the errors against the
  truth (rotation, degrees; translation, millimetres) and whether the two runs gave the same
  matrix to the last bit.
* ``filters``: :mod:`forestreg.engine.geometry.filters2d` against ``scipy.ndimage`` on random
  grids of a terrain model's sizes: time per call (median of several) and whether the results are
  equal to the last bit; and the time a fresh process spends importing ``scipy.ndimage``.
* ``nearest``: :class:`forestreg.engine.geometry.nearest.PlaneNearest` against
  ``scipy.spatial.cKDTree`` (build and query of a coarse match: a few dozen trunk positions, a
  million moved points), equality of distances and indices; the ICP's 3-D correspondence search
  (:class:`~forestreg.engine.geometry.features.SphereGrid`) against ``cKDTree`` on 300 000 points;
  and the import time of ``scipy.spatial``.

Threads: ``--threads N`` (default 2) sets ``OMP_NUM_THREADS`` (Open3D) and ``FORESTREG_THREADS``
(forestreg's kernels) before anything is imported. Each case runs well under a minute on 2 cores.

Run from the repository root::

    python -m benchmarks.icp_open3d                 # all three parts
    python -m benchmarks.icp_open3d --only icp      # one part (icp, filters, nearest)
    python -m benchmarks.icp_open3d --threads 1

Nothing is asserted: the figures are printed.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: the disturbance of the truth every ICP run starts from: metres, degrees
START_OFFSET_M, START_TURN_DEG = 0.3, 2.0


def _threads(n: int) -> None:
    os.environ["OMP_NUM_THREADS"] = str(n)
    os.environ["FORESTREG_THREADS"] = str(n)


def _disturbed(truth, offset_m: float, turn_deg: float, seed: int):
    """``truth`` moved by ``offset_m`` along a random direction and turned by ``turn_deg`` about a
    random axis (through the origin of the moving frame), as the start of a run."""
    import numpy as np

    from forestreg.engine.core.transform import rotation_from_vector

    rng = np.random.default_rng(seed)
    axis, direction = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
    step = np.eye(4)
    step[:3, :3] = rotation_from_vector(np.radians(turn_deg) * axis)
    step[:3, 3] = offset_m * direction
    return step @ truth


# --------------------------------------------------------------------------------------------- ICP


def simulated_case(preset: str, seed: int):
    """(reference points, moving points, true moving -> reference matrix) of two simulated TLS
    scans 10 m apart on a 30 m plot (0.4 deg step), each in its own scanner frame, metres."""
    from forestreg.engine.simulate.plot import simulate_plot

    plot = simulate_plot(preset, [(-5.0, 0.0), (5.0, 0.0)], angular_step_deg=0.4, size_m=30.0, seed=seed)
    return (
        plot.scans[0].scan.points.astype("float64"),
        plot.scans[1].scan.points.astype("float64"),
        plot.relative_pose(0, 1),
    )


def real_case():
    """(reference, moving, truth) from ``LPine1_demo.laz``: the points with x below 60 % of its
    extent (a random quarter) and those above 40 % (another quarter), the second moved by a yaw of
    25 degrees and (3, -2, 0.5) m; the truth maps the moved crop back."""
    import numpy as np

    from forestreg.engine.core.transform import apply, matrix_from_yaw
    from forestreg.engine.io import read_scan

    scan = read_scan(DATA / "LPine1_demo.laz", with_intensity=False)
    pts = np.asarray(scan.points, dtype=np.float64)
    lo, hi = pts[:, 0].min(), pts[:, 0].max()
    draw = np.random.default_rng(7).random(len(pts))
    ref = pts[(draw < 0.25) & (pts[:, 0] < lo + 0.6 * (hi - lo))]
    mov = pts[(draw > 0.75) & (pts[:, 0] > lo + 0.4 * (hi - lo))]
    motion = matrix_from_yaw(25.0, np.array([3.0, -2.0, 0.5]))
    return ref, apply(motion, mov), np.linalg.inv(motion)


def ours(ref, mov, initial):
    """forestreg's ICP with the pair registration's settings (no statistics: the matrix alone)."""
    from forestreg.engine.geometry.icp import icp
    from forestreg.engine.geometry.icp_params import IcpParams

    return icp(ref, mov, initial, statistics=False, **IcpParams().keywords()).matrix


def open3d_icp(ref, mov, initial, loss: str):
    """Open3D's point-to-plane ICP with the same stages as :func:`ours`: each stage thins both
    clouds to max(voxel, distance / 2.5), keeps a fixed random subset of at most
    ``max_moving_points`` moving points, estimates the reference's normals from 12 neighbours and
    runs at most 40 iterations with a ``loss`` ("tukey" or "huber") of scale = the distance."""
    import numpy as np
    import open3d as o3d

    from forestreg.engine.geometry.icp_params import IcpParams

    p = IcpParams()
    reg = o3d.pipelines.registration
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ref))
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(mov))
    matrix = np.asarray(initial, dtype=np.float64)
    rng = np.random.default_rng(0)
    for dist in p.max_distances_m:
        voxel = max(p.voxel_m, dist / 2.5)
        t = target.voxel_down_sample(voxel)
        s = source.voxel_down_sample(voxel)
        if len(s.points) > p.max_moving_points:
            s = s.select_by_index(np.sort(rng.choice(len(s.points), p.max_moving_points, replace=False)).tolist())
        t.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(p.normal_neighbours))
        kernel = reg.TukeyLoss(k=dist) if loss == "tukey" else reg.HuberLoss(k=dist)
        result = reg.registration_icp(
            s,
            t,
            dist,
            matrix,
            reg.TransformationEstimationPointToPlane(kernel),
            reg.ICPConvergenceCriteria(1e-6, 1e-6, p.iterations),
        )
        matrix = np.asarray(result.transformation)
    return matrix


def icp_table() -> list[list[str]]:
    import numpy as np

    from forestreg.engine.core.transform import rigid_errors

    methods: dict[str, Callable] = {
        "forestreg": ours,
        "open3d tukey": lambda r, m, i: open3d_icp(r, m, i, "tukey"),
        "open3d huber": lambda r, m, i: open3d_icp(r, m, i, "huber"),
    }
    cases = [
        ("sim mixed_temperate", lambda: simulated_case("mixed_temperate", 1)),
        ("sim planted_conifer", lambda: simulated_case("planted_conifer", 2)),
    ]
    if (DATA / "LPine1_demo.laz").exists():
        cases.append(("real LPine1 crops", real_case))
    else:
        print(f"(no {DATA / 'LPine1_demo.laz'}: the real case is left out)")
    rows = []
    for k, (name, make) in enumerate(cases):
        case_t0 = time.perf_counter()
        ref, mov, truth = make()
        start = _disturbed(truth, START_OFFSET_M, START_TURN_DEG, seed=k)
        size = f"{len(ref) / 1e3:.0f}k/{len(mov) / 1e3:.0f}k"
        for label, fn in methods.items():
            if label == "forestreg":
                fn(ref, mov, start)  # warm-up: the kernels loaded (Open3D is imported and compiled ahead)
            times, matrices = [], []
            for _ in range(2):
                t0 = time.perf_counter()
                matrices.append(fn(ref, mov, start))
                times.append(time.perf_counter() - t0)
            rot, trans = rigid_errors(matrices[0], truth)
            same = bool(np.array_equal(matrices[0], matrices[1]))
            rows.append(
                [
                    name,
                    size,
                    label,
                    f"{times[0]:.2f}",
                    f"{times[1]:.2f}",
                    f"{rot:.4f}",
                    f"{1000 * trans:.1f}",
                    "yes" if same else f"no ({np.abs(matrices[0] - matrices[1]).max():.1e})",
                ]
            )
        print(f"  {name}: {time.perf_counter() - case_t0:.0f} s with making the clouds", file=sys.stderr)
    return [
        ["case", "points ref/mov", "method", "run 1 s", "run 2 s", "rot err deg", "trans err mm", "bit-equal"]
    ] + rows


# ----------------------------------------------------------------------------------------- filters


def _median_time(fn: Callable, repeat: int = 7) -> float:
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _import_time(module: str, runs: int = 3) -> float:
    """Median seconds a fresh interpreter (NumPy already imported) spends importing ``module``."""
    code = f"import numpy, time; t = time.perf_counter(); import {module}; print(time.perf_counter() - t)"
    return statistics.median(
        float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
        for _ in range(runs)
    )


def filters_table() -> list[list[str]]:
    import numpy as np
    from scipy import ndimage

    from forestreg.engine.geometry import filters2d as f

    rows = []
    for n in (120, 400):  # 60 m and 200 m of ground at the ground grid's 0.5 m cells
        rng = np.random.default_rng(n)
        grid = np.round(rng.normal(size=(n, n + 7)), 2)  # rounded: ties, as heights in centimetres
        missing = rng.random(grid.shape) < 0.3
        cases = [
            (
                "minimum 7x7",
                lambda: f.minimum_filter_nearest(grid, 7),
                lambda: ndimage.minimum_filter(grid, 7, mode="nearest"),
            ),
            (
                "median 3x3",
                lambda: f.median3_nearest(grid),
                lambda: ndimage.median_filter(grid, size=3, mode="nearest"),
            ),
            (
                "nearest cell",
                lambda: f.nearest_cell_indices(missing),
                lambda: tuple(ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)),
            ),
            (
                "gaussian s=2",
                lambda: f.gaussian_smooth(grid, 2.0),
                lambda: ndimage.gaussian_filter(grid, 2.0, mode="constant"),
            ),
        ]
        for name, mine, theirs in cases:
            a, b = mine(), theirs()
            equal = all(np.array_equal(x, y) for x, y in zip(a, b)) if isinstance(a, tuple) else np.array_equal(a, b)
            t_mine, t_theirs = _median_time(mine), _median_time(theirs)
            rows.append(
                [
                    name,
                    f"{n}x{n + 7}",
                    f"{1000 * t_mine:.2f}",
                    f"{1000 * t_theirs:.2f}",
                    f"{t_mine / t_theirs:.2f}",
                    "yes" if equal else "no",
                ]
            )
    rows.append(["import scipy.ndimage", "fresh process", "", f"{1000 * _import_time('scipy.ndimage'):.0f}", "", ""])
    return [["filter", "grid", "forestreg ms", "scipy ms", "ratio", "bit-equal"]] + rows


# ----------------------------------------------------------------------------------------- nearest


def nearest_table() -> list[list[str]]:
    import numpy as np
    from scipy.spatial import cKDTree

    from forestreg.engine.geometry.nearest import PlaneNearest

    rows = []
    for n_ref, n_query in ((40, 1_000_000), (400, 1_000_000)):
        rng = np.random.default_rng(n_ref)
        ref = np.round(rng.uniform(-20, 20, size=(n_ref, 2)), 3)
        query = np.round(rng.uniform(-21, 21, size=(n_query, 2)), 3)
        dist = 0.5

        def mine():
            return PlaneNearest(ref, dist).query(query)

        def theirs():
            return cKDTree(ref).query(query, distance_upper_bound=dist, workers=int(os.environ["FORESTREG_THREADS"]))

        (d1, i1), (d2, i2) = mine(), theirs()
        same_d = bool(np.array_equal(d1, d2))
        differ = int((i1 != i2).sum())
        t_mine, t_theirs = _median_time(mine, 5), _median_time(theirs, 5)
        rows.append(
            [
                f"{n_ref} refs",
                f"{n_query / 1e6:.0f} M",
                f"{1000 * t_mine:.1f}",
                f"{1000 * t_theirs:.1f}",
                f"{t_mine / t_theirs:.2f}",
                "yes" if same_d else "no",
                str(differ),
            ]
        )
    rows.append(icp_search_row())
    rows.append(
        ["import scipy.spatial", "fresh process", "", f"{1000 * _import_time('scipy.spatial'):.0f}", "", "", ""]
    )
    return [
        ["reference", "queries", "forestreg ms", "cKDTree ms", "ratio", "distances bit-equal", "indices differing"]
    ] + rows


def icp_search_row() -> list[str]:
    """The ICP's correspondence search in 3-D (:class:`~forestreg.engine.geometry.features.SphereGrid`
    and :func:`~forestreg.engine.geometry.features.nearest_within`) against ``cKDTree``: a grid
    (tree) built on 300 000 points of a forest-like scene (stems as vertical cylinders on a
    ground), then 10 searches (an ICP stage's iterations) of 30 000 points within 0.08 m."""
    import numpy as np
    from scipy.spatial import cKDTree

    from forestreg.engine.geometry.features import SphereGrid, nearest_within, query_order

    rng = np.random.default_rng(3)
    n = 300_000
    ground = np.column_stack([rng.uniform(-15, 15, (n // 2, 2)), rng.normal(0, 0.02, n // 2)])
    centres, angle = rng.uniform(-14, 14, (60, 2)), rng.uniform(0, 2 * np.pi, n // 2)
    stem = rng.integers(0, 60, n // 2)
    stems = np.column_stack(
        [centres[stem] + 0.15 * np.column_stack([np.cos(angle), np.sin(angle)]), rng.uniform(0, 12, n // 2)]
    )
    ref = np.round(np.vstack([ground, stems]), 3)
    query = ref[rng.choice(n, 30_000, replace=False)] + rng.normal(0, 0.02, (30_000, 3))
    workers = int(os.environ["FORESTREG_THREADS"])

    def mine():
        grid = SphereGrid(ref, 2.5 * 0.05)  # the finest stage's cells: 2.5 voxels of 0.05 m
        order = query_order(query, grid)
        return [nearest_within(query, grid, 0.08, order=order) for _ in range(10)][-1]

    def theirs():
        tree = cKDTree(ref)
        return [tree.query(query, distance_upper_bound=0.08, workers=workers) for _ in range(10)][-1]

    (d1, i1), (d2, i2) = mine(), theirs()
    t_mine, t_theirs = _median_time(mine, 3), _median_time(theirs, 3)
    return [
        "3-D, 300k points",
        "10 x 30k",
        f"{1000 * t_mine:.1f}",
        f"{1000 * t_theirs:.1f}",
        f"{t_mine / t_theirs:.2f}",
        "yes" if np.array_equal(d1, d2) else "no",
        str(int((i1 != i2).sum())),
    ]


def _print(title: str, table: list[list[str]]) -> None:
    widths = [max(len(r[k]) for r in table) for k in range(len(table[0]))]
    print(f"\n{title}")
    for k, row in enumerate(table):
        print("| " + " | ".join(c.ljust(w) for c, w in zip(row, widths)) + " |")
        if k == 0:
            print("|" + "|".join("-" * (w + 2) for w in widths) + "|")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.icp_open3d", description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", choices=("icp", "filters", "nearest"), help="one part only")
    ap.add_argument(
        "--threads", type=int, default=2, help="threads of Open3D and of forestreg's kernels (default %(default)s)"
    )
    args = ap.parse_args(argv)
    _threads(args.threads)
    if args.only in (None, "icp"):
        import open3d as o3d

        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        _print(f"ICP ({args.threads} threads; start: truth + {START_OFFSET_M} m, {START_TURN_DEG} deg)", icp_table())
    if args.only in (None, "filters"):
        _print("2-D filters (median of 7 calls)", filters_table())
    if args.only in (None, "nearest"):
        _print(f"nearest points ({args.threads} threads; build + query)", nearest_table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
