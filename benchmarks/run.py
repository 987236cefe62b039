"""forestreg benchmarks: pair registration per step and against Sylva, a 4-scan plot, memory, the coarse matcher, System B.

Run from the repository root (about 30 minutes on 2 cores with the 30 M-point scan, without the ten-scan
plot of `--only bigplot`; `--quick`: a few minutes)::

    .venv/bin/python benchmarks/run.py            # or: python -m benchmarks.run
    .venv/bin/python benchmarks/run.py --quick    # smoke run: skips the ~3 M point pair
    .venv/bin/python benchmarks/run.py --json bench.json --seed 3

1. Pair registration: a simulated ``mixed_temperate`` plot (60 m side), two scanners 12 m apart,
   at 0.1 deg angular step (about 3 M points per scan) and at 0.25 deg (about 0.45 M points per
   scan). Each scan is simulated, written to LAZ and read back in a temporary folder (the I/O a
   user pays), then the read-back scans are registered with the default parameters; the steps
   come from ``PairResult.timings``. Accuracy is checked against the simulator's truth.
2. The exact coarse VOP matcher vs the paper's literal enumeration, from
   :func:`benchmarks.coarse_matcher.run` (20/40/80 VOPs, 0.1 deg).
3. Whole commands side by side (:mod:`benchmarks.peers`): reading both LAZ files, ``forestreg
   register`` and Sylva's ``coreg`` (``pip install 'forestreg[bench]'``) on the same simulated
   pairs, in turn, with wall time and peak memory per process and their run-by-run ratios.
4. A 4-scan plot, every pair registered (:mod:`benchmarks.plot_speed`): ``forestreg plot --pairs
   all`` against Sylva's multi-scan ``coreg`` (left out by ``--quick``).
5. Peak memory of ``forestreg register`` on a ~30 M-point scan (:mod:`benchmarks.big_scan`; long:
   left out by ``--quick``).
6. System B at full size (:mod:`benchmarks.system_b`): ground-based/UAV co-registration, fusion
   and the tree inventory of the fused cloud.
7. Peak memory of System B's commands (``coregister``, ``fuse``, ``trees``; ``trees`` also on
   each real cloud of ``../shared/data``) against the budget of 3x their raw point arrays + 300
   MB (:mod:`benchmarks.command_memory`; left out by ``--quick``).
8. Trees side by side with Sylva (:mod:`benchmarks.trees_compare`): ``forestreg trees`` against
   ``sylva ground`` + ``sylva trees`` and ``sylva qsm`` on the same simulated (with truth) and real
   clouds: found, false stems, DBH, height, volume, time and memory; the real single trees'
   cylinder models beside ``sylva qsm`` and the TreeQSM port's stored figures (total and stem).
9. A re-survey (:mod:`benchmarks.resurvey`): a simulated stand measured again six years later,
   ``forestreg change`` against the simulator's truth (registration error, statuses, growth).
10. A plot of ten ~30 M-point scans registered and merged into one COPC file within 4 GB
   (:mod:`benchmarks.big_plot`; about an hour: only with ``--only bigplot``, left out by default
   and by ``--quick``).
11. The pair at scale (:mod:`benchmarks.scaling`): reading both files, ``forestreg register`` and
   Sylva's ``coreg`` on pairs of 1, 3, 10, 30 and 50 M points per scan (``--sizes``; ``--quick``:
   0.1, 0.3 and 1 M), time, peak memory, ratios and errors against the truth (about 20 minutes
   on 2 cores; only with ``--only scaling``).
12. ``forestreg batch`` of 20 small simulated plots with 1 and with 2 local Dask workers: wall time,
   speed-up, memory per plot (:mod:`benchmarks.batch_scaling`; only with ``--only batch``).
13. Trees at scale (:mod:`benchmarks.trees_scale`): ``forestreg trees`` on a 2.9 M-point plot and on
   the same plot densified to 32 M points, with and without cylinder models, beside Sylva's
   ``ground`` + ``trees`` and reading the file: time, peak memory, ratios, accuracy against the
   truth (about 10 minutes on 2 cores; only with ``--only treescale``).
14. Calibration of the stated uncertainty (:mod:`benchmarks.calibration`): ~100 pairs drawn afresh
   from a seed over every kind of scene (built scenes, planted rows, forward-looking and 300 deg
   scanners, the forest presets, real clouds moved by known transforms); every "ok"'s true error
   over its stated sigma, the "ok" beyond 3 sigma, the refusal rate per kind (about 15-25 minutes
   on 2 cores, ``--quick``: one case per kind; only with ``--only calibration``; its seed
   ``--calibration-seed``, default drawn and printed).

Timings are wall-clock seconds of one run (``time.perf_counter``); nothing is asserted on them.
An untimed warm-up (a coarse 0.5 deg pair) runs first so imports and library initialisation do
not land in the first timed step.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np

if __package__:
    from . import (
        batch_scaling,
        big_plot,
        big_scan,
        calibration,
        coarse_matcher,
        command_memory,
        peers,
        plot_speed,
        resurvey,
        scaling,
        system_b,
        trees_compare,
        trees_scale,
    )
else:  # run as a script: python benchmarks/run.py
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import batch_scaling  # type: ignore[no-redef]
    import big_plot  # type: ignore[no-redef]
    import big_scan  # type: ignore[no-redef]
    import calibration  # type: ignore[no-redef]
    import coarse_matcher  # type: ignore[no-redef]
    import command_memory  # type: ignore[no-redef]
    import peers  # type: ignore[no-redef]
    import plot_speed  # type: ignore[no-redef]
    import resurvey  # type: ignore[no-redef]
    import scaling  # type: ignore[no-redef]
    import system_b  # type: ignore[no-redef]
    import trees_compare  # type: ignore[no-redef]
    import trees_scale  # type: ignore[no-redef]

from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.io import read_scan, write_scan
from forestreg.engine.simulate import simulate_plot
from forestreg.engine.tls.pair import register

PRESET = "mixed_temperate"
SIZE_M = 60.0
SEPARATION_M = 12.0
#: (label, angular step deg); the first is the ~3 M point pair that --quick skips.
PAIRS = (("large", 0.1), ("small", 0.25))
REGISTRATION_STEPS = ("prepare_reference_s", "prepare_moving_s", "slice_s", "vops_s", "coarse_s", "vertical_s", "icp_s")


# ------------------------------------------------------------------------------------- environment


def environment() -> dict[str, Any]:
    """Cores and thread pools available to this process."""
    info: dict[str, Any] = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "usable_cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "thread_env": {
            k: os.environ[k] for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS") if k in os.environ
        },
        "numpy": np.__version__,
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }
    try:  # the version without importing it: ~200 MB this process would hold, which every child
        # measured later would count (a child's ru_maxrss starts at its parent's high-water mark)
        from importlib.metadata import version

        info["open3d"] = version("open3d")
    except Exception:  # pragma: no cover - open3d is a dependency
        pass
    try:
        from threadpoolctl import threadpool_info

        info["threadpools"] = [
            {k: p.get(k) for k in ("user_api", "internal_api", "num_threads", "version", "prefix")}
            for p in threadpool_info()
        ]
    except ImportError:
        info["threadpools"] = None
    return info


def _format_environment(env: dict[str, Any]) -> str:
    lines = [
        f"forestreg benchmarks - Python {env['python']} on {env['platform']}",
        f"cores: os.cpu_count() = {env['cpu_count']}, usable by this process = {env['usable_cpus']}"
        + (f", thread env {env['thread_env']}" if env["thread_env"] else "")
        + (
            f"; 1-min load average at start {env['load_average_1min']:.2f}"
            if env["load_average_1min"] is not None
            else ""
        ),
    ]
    if env["threadpools"] is None:
        lines.append("thread pools: threadpoolctl not installed")
    elif not env["threadpools"]:
        lines.append("thread pools: none loaded")
    else:
        pools = ", ".join(
            f"{p['internal_api']} {p['version']} ({p['user_api']}) {p['num_threads']} threads"
            for p in env["threadpools"]
        )
        lines.append(f"thread pools (threadpoolctl): {pools}")
    lines.append(f"numpy {env['numpy']}" + (f", open3d {env['open3d']}" if "open3d" in env else ""))
    return "\n".join(lines)


# ------------------------------------------------------------------------------ pair registration


def _positions() -> list[tuple[float, float]]:
    half = SEPARATION_M / 2.0
    return [(-half, 0.0), (half, 0.0)]


def bench_pair(label: str, angular_step_deg: float, seed: int, workdir: Path) -> dict[str, Any]:
    """Simulate, write + read LAZ, register one pair; every cost in seconds."""
    marks: list[tuple[float, str]] = []
    t0 = time.perf_counter()
    plot = simulate_plot(
        PRESET,
        _positions(),
        seed=seed,
        angular_step_deg=angular_step_deg,
        size_m=SIZE_M,
        progress=lambda f, m: marks.append((time.perf_counter(), m)),
    )
    t_end = time.perf_counter()
    # progress marks: "scanning scan_01 (1/2)", "scanning scan_02 (2/2)", "done"
    starts = [t for t, m in marks if m.startswith("scanning ")]
    simulate = {
        "scene": starts[0] - t0,
        "scan_01": starts[1] - starts[0],
        "scan_02": t_end - starts[1],
    }
    truth = plot.relative_pose(0, 1)
    points = [len(s.scan.points) for s in plot.scans]

    write_s, read_s, laz_mb, scans = [], [], [], []
    for i, sim in enumerate(plot.scans):
        path = workdir / f"{label}_scan_{i + 1:02d}.laz"
        t = time.perf_counter()
        write_scan(sim.scan, path)
        write_s.append(time.perf_counter() - t)
        laz_mb.append(path.stat().st_size / 1e6)
    del plot, sim  # registration works on the read-back scans only
    for i in range(2):
        path = workdir / f"{label}_scan_{i + 1:02d}.laz"
        t = time.perf_counter()
        scans.append(read_scan(path))
        read_s.append(time.perf_counter() - t)

    t = time.perf_counter()
    result = register(scans[0], scans[1])
    register_wall = time.perf_counter() - t
    timings = {k: float(result.timings.get(k, 0.0)) for k in REGISTRATION_STEPS}
    timings.update({k: float(v) for k, v in result.timings.items() if k not in timings})

    row: dict[str, Any] = {
        "label": label,
        "preset": PRESET,
        "seed": seed,
        "size_m": SIZE_M,
        "separation_m": SEPARATION_M,
        "angular_step_deg": angular_step_deg,
        "points": points,
        "laz_mb": laz_mb,
        "simulate_s": simulate,
        "write_laz_s": write_s,
        "read_laz_s": read_s,
        "registration_s": timings,
        "registration_total_s": float(sum(timings.values())),
        "registration_wall_s": register_wall,
        "status": result.status,
        "reason": result.reason,
        "matched": result.matched,
        "second_matched": result.second_matched,
        "reference_vops": result.reference_vops,
        "moving_vops": result.moving_vops,
        "vop_radius_m": result.vop_radius_m,
        "icp_std_m": None if result.icp is None else float(result.icp.std_m),
        "final_error": None,
        "coarse_error": None,
    }
    if result.matrix is not None:
        row["final_error"] = dict(zip(("rotation_deg", "translation_m"), rigid_errors(result.matrix, truth)))
    if result.coarse_matrix is not None:
        row["coarse_error"] = dict(zip(("rotation_deg", "translation_m"), rigid_errors(result.coarse_matrix, truth)))
    return row


def _warm_up(seed: int, workdir: Path) -> None:
    """Untimed: load Open3D/laspy/scipy code paths once (its outcome does not matter: silenced)."""
    logger = logging.getLogger("forestreg")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        plot = simulate_plot(PRESET, _positions(), seed=seed, angular_step_deg=0.5, size_m=SIZE_M)
        path = workdir / "warmup.laz"
        write_scan(plot.scans[0].scan, path)
        read_scan(path)
        register(plot.scans[0].scan, plot.scans[1].scan)
    finally:
        logger.setLevel(level)


def _format_pairs(rows: list[dict[str, Any]]) -> str:
    width = 17
    label_w = 36

    def line(label: str, values: list[str]) -> str:
        return f"{label:<{label_w}}" + "".join(f"{v:>{width}}" for v in values)

    def secs(v: float) -> str:
        return f"{v:.2f}"

    lines = [
        f"Pair registration: simulated {PRESET}, {SIZE_M:.0f} m plot, scanners {SEPARATION_M:.0f} m apart "
        "(wall-clock seconds)",
        line("", [f"step {r['angular_step_deg']:.2f} deg" for r in rows]),
        line(
            "points per scan (ref / moving)",
            [f"{r['points'][0] / 1e6:.2f} / {r['points'][1] / 1e6:.2f} M" for r in rows],
        ),
    ]
    lines.append("-" * (label_w + width * len(rows)))
    lines.append(line("simulate: scene meshes", [secs(r["simulate_s"]["scene"]) for r in rows]))
    lines.append(line("simulate scan_01 (+ lazy BVH build)", [secs(r["simulate_s"]["scan_01"]) for r in rows]))
    lines.append(line("simulate scan_02", [secs(r["simulate_s"]["scan_02"]) for r in rows]))
    for i, name in enumerate(("scan_01", "scan_02")):
        lines.append(line(f"write LAZ {name}", [secs(r["write_laz_s"][i]) for r in rows]))
    for i, name in enumerate(("scan_01", "scan_02")):
        lines.append(line(f"read LAZ {name}", [secs(r["read_laz_s"][i]) for r in rows]))
    lines.append("-" * (label_w + width * len(rows)))
    steps = list(REGISTRATION_STEPS) + sorted({k for r in rows for k in r["registration_s"]} - set(REGISTRATION_STEPS))
    for k in steps:
        lines.append(line(f"register: {k}", [secs(r["registration_s"].get(k, 0.0)) for r in rows]))
    lines.append(line("register: total", [secs(r["registration_total_s"]) for r in rows]))
    lines.append(
        line(
            "read both + register (user's cost)", [secs(sum(r["read_laz_s"]) + r["registration_total_s"]) for r in rows]
        )
    )
    lines.append("-" * (label_w + width * len(rows)))
    for r in rows:
        head = f"step {r['angular_step_deg']:.2f} deg: "
        if r["status"] != "ok":
            lines.append(head + f"FAILED ({r['reason']})")
            continue
        fe, ce = r["final_error"], r["coarse_error"]
        lines.append(
            head + f"error vs truth: final {fe['rotation_deg']:.3f} deg / {fe['translation_m'] * 1000:.1f} mm, "
            f"coarse {ce['rotation_deg']:.3f} deg / {ce['translation_m'] * 1000:.1f} mm"
        )
        lines.append(
            " " * len(head) + f"matched VOPs {r['matched']} of {r['reference_vops']}/{r['moving_vops']} "
            f"(next distinct {r['second_matched']}, D_r {r['vop_radius_m']:.0f} m), "
            f"ICP std {r['icp_std_m'] * 1000:.1f} mm, LAZ {r['laz_mb'][0]:.1f}+{r['laz_mb'][1]:.1f} MB"
        )
    return "\n".join(lines)


# ----------------------------------------------------------------------------------- coarse matcher


def _format_coarse(rows: list[dict[str, Any]]) -> str:
    step = rows[0]["angle_step_deg"] if rows else 0.1
    head = (
        f"{'VOPs':>5} {'fast s':>8} {'literal s':>10} {'extrapolated':>12} {'ratio':>9} "
        f"{'scores computed':>15} {'of (literal)':>12} {'matched':>7} {'rot err deg':>11}"
    )
    lines = [
        f"Coarse matcher: exact branch-and-bound vs the paper's literal enumeration ({step} deg steps; "
        "fast = median of runs)",
        head,
        "-" * len(head),
    ]
    for r in rows:
        lines.append(
            f"{r['size']:>5} {r['fast_s']:>8.3f} {r['literal_s']:>10.1f} {'yes' if r['literal_extrapolated'] else 'no':>12} "
            f"{r['ratio']:>9.0f} {r.get('evaluated', ''):>15} {r.get('literal_evaluated', ''):>12} "
            f"{r.get('matched', ''):>7} {r.get('rotation_error_deg', float('nan')):>11.3f}"
        )
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------- main


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON-able: {type(o).__name__}")


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="skip the ~3 M point pair (smoke run)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated plot and of the VOP sets (default 0)")
    ap.add_argument("--json", metavar="FILE", type=Path, help="also write every row to this JSON file")
    ap.add_argument("--runs", type=int, default=3, help="timed rounds of the whole-command comparison (default 3)")
    ap.add_argument(
        "--only",
        choices=(
            "pairs",
            "peers",
            "plot",
            "big",
            "bigplot",
            "coarse",
            "system_b",
            "commands",
            "trees",
            "resurvey",
            "scaling",
            "batch",
            "treescale",
            "calibration",
        ),
        action="append",
        help="run only these parts (repeatable; default all but bigplot; --quick leaves out plot, big and commands). "
        "bigplot: ten ~30 M-point scans registered and merged as COPC, about an hour, so only when named; "
        "scaling: the pair at 1-50 M points per scan beside Sylva and reading, only when named; "
        "batch: 20 small plots on 1 and 2 local Dask workers, only when named; "
        "treescale: trees of a 32 M-point plot beside Sylva and reading, about 10 minutes, only when named; "
        "calibration: the stated uncertainty against the truth on ~100 fresh pairs, only when named",
    )
    ap.add_argument(
        "--calibration-seed", type=int, help="calibration: the seed of its cases (default: drawn afresh and printed)"
    )
    ap.add_argument(
        "--sizes", help="scaling: points per scan, millions, comma-separated (default 1,3,10,30,50; --quick 0.1,0.3,1)"
    )
    ap.add_argument(
        "--workdir",
        type=Path,
        help="bigplot, scaling, batch and treescale: keep their simulated and densified scans here (default bench_out/; reused)",
    )
    args = ap.parse_args(argv)

    t_start = time.perf_counter()
    env = environment()
    print(_format_environment(env))
    print(f"seed {args.seed}{', quick (no ~3 M point pair)' if args.quick else ''}", flush=True)
    print()

    parts = set(
        args.only
        or (
            ("pairs", "peers", "coarse", "system_b", "trees", "resurvey")
            if args.quick
            else ("pairs", "peers", "plot", "big", "coarse", "system_b", "commands", "trees", "resurvey")
        )
    )
    pair_rows: list[dict[str, Any]] = []
    peer_rows: list[dict[str, Any]] = []
    coarse_rows: list[dict[str, Any]] = []
    system_b_rows: Any = []
    # the child processes' peaks come first, while this process is small: the kernel counts the
    # parent's memory at the fork in a child's peak (ru_maxrss), and every part below grows this
    # process (reading the files in-process: ~600 MB after the peers, ~2 GB after the pairs)
    command_rows: list[dict[str, Any]] = []
    if "commands" in parts:
        command_rows = command_memory.run(runs=args.runs)
        print(command_memory.format_rows(command_rows))
        print(flush=True)
    trees_rows: list[dict[str, Any]] = []
    if "trees" in parts:  # child processes too: while this process is small
        trees_rows = trees_compare.run()
        print(trees_compare.format_rows(trees_rows))
        print()
        print(trees_compare.single_tree_table(trees_rows))
        print(flush=True)
    if "peers" in parts:
        peer_rows = peers.run(quick=args.quick, runs=args.runs)
        print(peers.format_rows(peer_rows))
        print(flush=True)
    plot_row: Optional[dict[str, Any]] = None
    if "plot" in parts:
        with tempfile.TemporaryDirectory(prefix="forestreg-plot-") as tmp:
            plot_row = plot_speed.run(runs=max(1, args.runs - 1), workdir=Path(tmp))
        print(plot_speed.format_row(plot_row))
        print(flush=True)
    big_row: Optional[dict[str, Any]] = None
    if "big" in parts:
        big_row = big_scan.run()
        print(big_scan.format_row(big_row))
        print(flush=True)
    scaling_rows: list[dict[str, Any]] = []
    if "scaling" in parts:  # child processes: while this process is small
        sizes = (
            tuple(float(v) for v in args.sizes.split(","))
            if args.sizes
            else (scaling.QUICK_SIZES_M if args.quick else scaling.SIZES_M)
        )
        # one round a size (the large ones take minutes); --quick: --runs rounds of its small sizes
        scaling_rows = scaling.run(
            sizes, runs=args.runs if args.quick else 1, workdir=(args.workdir / "scaling") if args.workdir else None
        )
        print()
        print(scaling.format_rows(scaling_rows))
        print(flush=True)
    big_plot_row: Optional[dict[str, Any]] = None
    if "bigplot" in parts:
        big_plot_row = big_plot.run(workdir=args.workdir)
        print(big_plot.format_row(big_plot_row))
        print(flush=True)
    batch_row: Optional[dict[str, Any]] = None
    if "batch" in parts:  # only when named: 1 and 2 local workers on 20 plots
        batch_row = batch_scaling.run(workdir=args.workdir or Path("bench_out"))
        print(batch_scaling.format_row(batch_row))
        print(flush=True)
    tree_scale_rows: list[dict[str, Any]] = []
    if "treescale" in parts:  # only when named: child processes, while this process is small
        tree_scale_rows = trees_scale.run(workdir=(args.workdir / "trees_scale") if args.workdir else None)
        print(trees_scale.format_rows(tree_scale_rows))
        print(flush=True)
    if "pairs" in parts:
        pairs = PAIRS[1:] if args.quick else PAIRS
        with tempfile.TemporaryDirectory(prefix="forestreg-bench-") as tmp:
            workdir = Path(tmp)
            _warm_up(args.seed, workdir)
            for label, step in pairs:
                pair_rows.append(bench_pair(label, step, args.seed, workdir))
                for f in workdir.glob(f"{label}_*.laz"):
                    f.unlink()
        print(_format_pairs(pair_rows))
        print(flush=True)
    if "coarse" in parts:
        coarse_rows = coarse_matcher.run(sizes=(20, 40, 80), angle_step_deg=0.1, seed=args.seed)
        print(_format_coarse(coarse_rows))
        print(flush=True)
    if "system_b" in parts:
        system_b_rows = system_b.run(seed=args.seed, quick=args.quick)
        print(system_b.format_rows(system_b_rows))
        print()
    resurvey_rows: list[dict[str, Any]] = []
    if "resurvey" in parts:
        resurvey_rows = resurvey.run(
            seeds=resurvey.HELD_OUT_SEEDS[:1], quick=args.quick, scans=(2, 5) if args.quick else (2, 3, 5)
        )
        print(resurvey.format_rows(resurvey_rows))
        print(flush=True)
    calibration_run: Optional[dict[str, Any]] = None
    if "calibration" in parts:  # only when named
        calibration_run = calibration.run(args.calibration_seed, quick=args.quick)
        print()
        print(calibration.format_report(calibration_run["rows"], calibration_run["summary"]))
        print(
            f"calibration: seed {calibration_run['seed']}, {calibration_run['n']} cases, {calibration_run['wall_s']:.0f} s",
            flush=True,
        )
    wall = time.perf_counter() - t_start
    print(f"total benchmark wall time {wall:.0f} s")

    if args.json is not None:
        payload = {
            "environment": env,
            "seed": args.seed,
            "quick": args.quick,
            "wall_s": wall,
            "pairs": pair_rows,
            "peers": peer_rows,
            "plot": plot_row,
            "big_scan": big_row,
            "big_plot": big_plot_row,
            "coarse_matcher": coarse_rows,
            "system_b": system_b_rows,
            "commands": command_rows,
            "trees_compare": trees_rows,
            "resurvey": resurvey_rows,
            "scaling": scaling_rows,
            "batch": batch_row,
            "trees_scale": tree_scale_rows,
            "calibration": calibration_run,
        }
        args.json.write_text(json.dumps(payload, indent=2, default=_jsonable) + "\n")
        print(f"rows written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
