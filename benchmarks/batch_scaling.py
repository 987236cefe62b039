"""Benchmark: ``forestreg batch`` of 20 simulated plots with 1 and with 2 local Dask workers.

The plots: 20 simulated ``planted_conifer`` plots of 40 m side, each scanned from three positions
at 0.25 deg (about 0.4 M points per scan), seeds 1..20, simulated once into ``--workdir`` (reused).
The same batch then runs as a whole command (``forestreg batch PLOTS --out OUT --workers N
--threads 1``, a child process: cluster start-up, 20 plot processes, summary) with 1 worker and
with 2 workers, in turn, ``--rounds`` times (the order swapped every round); each plot's process
runs one thread, so N workers use N cores. Reported per run: wall time from the parent's clock,
the 1-minute load average before and after (the machine may be shared), the CPU time of the whole process tree (over the wall time:
the cores the batch got), the plots' wall times summed over the batch's (the plots running at
once: how busy the batch kept its workers, whatever the machine gave them), and from the
batch's ``summary.csv`` each plot's wall time, CPU time and peak memory (its process tree's
high-water mark). Speed-up = wall(1 worker) / wall(2 workers) of the same round. Accuracy: every
plot's poses against the simulator's truth (the largest rotation and translation error).

Run: ``python -m benchmarks.batch_scaling [--rounds N] [--workdir DIR] [--plots 20]`` or
``python benchmarks/run.py --only batch`` (about 6 minutes on 2 quiet cores, plus about 2 for
the first simulation).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np

if __package__:
    from . import peers
else:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import peers  # type: ignore[no-redef]

POSITIONS = [(0.0, 0.0), (9.0, 4.0), (-3.0, 9.0)]
PRESET = "planted_conifer"
STEP_DEG = 0.25
SIZE_M = 40.0


def _env() -> dict[str, str]:
    import forestreg

    env = dict(os.environ)
    package = Path(forestreg.__file__).parent
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(package.parent), env.get("PYTHONPATH", "")) if p)
    return env


def simulate(workdir: Path, plots: int = 20) -> Path:
    """``workdir/batch_plots/plot_NN/`` (scans + truth.json), simulated when missing."""
    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import simulate_plot

    root = workdir / "batch_plots"
    root.mkdir(parents=True, exist_ok=True)
    for k in range(1, plots + 1):
        folder = root / f"plot_{k:02d}"
        if not (folder / "truth.json").is_file():
            write_simulated_plot(
                simulate_plot(PRESET, POSITIONS, seed=k, angular_step_deg=STEP_DEG, size_m=SIZE_M), folder
            )
    for extra in sorted(root.iterdir()):  # fewer plots asked than simulated before
        if extra.is_dir() and extra.name.startswith("plot_") and int(extra.name[5:]) > plots:
            shutil.rmtree(extra)
    return root


def _truth(folder: Path) -> dict[str, np.ndarray]:
    scans = json.loads((folder / "truth.json").read_text())["scans"]
    first = np.linalg.inv(np.array(scans[0]["matrix"], dtype=float))
    return {f"{s['name']}.laz": first @ np.array(s["matrix"], dtype=float) for s in scans}


def _worst_error(plots: Path, out: Path) -> dict[str, Any]:
    from forestreg.engine.core.transform import rigid_errors

    rot, trans, missing = 0.0, 0.0, 0
    for folder in sorted(p for p in plots.iterdir() if p.is_dir()):
        truth = _truth(folder)
        try:
            poses = json.loads((out / folder.name / "poses.json").read_text())["scans"]
        except (OSError, ValueError, KeyError):
            missing += len(truth) - 1
            continue
        for name, pose in poses.items():
            if name == "scan_01.laz":
                continue
            if pose.get("matrix") is None:
                missing += 1
                continue
            r, t = rigid_errors(np.array(pose["matrix"], dtype=float), truth[name])
            rot, trans = max(rot, r), max(trans, t)
    return {"rotation_deg": rot, "translation_m": trans, "unregistered": missing}


def run_batch(plots: Path, out: Path, workers: int) -> dict[str, Any]:
    """One whole ``forestreg batch`` command; its wall time, load and CPU, and its summary."""
    if out.exists():
        shutil.rmtree(out)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "forestreg.cli",
            "batch",
            str(plots),
            "--out",
            str(out),
            "--workers",
            str(workers),
            "--threads",
            "1",
            "--quiet",
        ],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=7200,
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    with (out / "summary.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    peaks = [float(r["peak_mb"]) for r in rows if r["peak_mb"]]
    return {
        "workers": workers,
        "exit_code": run.returncode,
        "wall_s": wall,
        "load_before": load_before,
        "load_after": os.getloadavg()[0],
        "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
        "plots": len(rows),
        "ok": sum(r["status"] == "ok" for r in rows),
        "plot_seconds": [float(r["seconds"]) for r in rows if r["seconds"]],
        "plot_cpu_s": [float(r["cpu_s"]) for r in rows if r["cpu_s"]],
        "plot_peak_mb": peaks,
        "error": _worst_error(plots, out),
        "stderr": run.stderr[-2000:] if run.returncode else "",
    }


def run(workdir: Optional[Path] = None, rounds: int = 1, plots: int = 20) -> dict[str, Any]:
    """Simulate (once) and time the batch with 1 and 2 workers, ``rounds`` times in turn."""
    workdir = Path(workdir or "bench_out")
    t = time.perf_counter()
    root = simulate(workdir, plots)
    simulate_s = time.perf_counter() - t
    points = [int(s["n_points"]) for s in json.loads((root / "plot_01" / "truth.json").read_text())["scans"]]
    runs: list[dict[str, Any]] = []
    for k in range(rounds):  # in turn, the order swapped every round (a drifting load favours neither)
        for workers in (1, 2) if k % 2 == 0 else (2, 1):
            runs.append(run_batch(root, workdir / f"batch_out_{workers}", workers))
    one = [r for r in runs if r["workers"] == 1]
    two = [r for r in runs if r["workers"] == 2]
    return {
        "plots": plots,
        "preset": PRESET,
        "step_deg": STEP_DEG,
        "size_m": SIZE_M,
        "scans_per_plot": len(POSITIONS),
        "points_per_scan": points,
        "simulate_s": simulate_s,
        "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "runs": runs,
        "speedup": [a["wall_s"] / b["wall_s"] for a, b in zip(one, two)],
    }


def format_row(row: dict[str, Any]) -> str:
    lines = [
        f"Batch scaling: {row['plots']} simulated {row['preset']} plots ({row['size_m']:.0f} m, {row['scans_per_plot']} scans at "
        f"{row['step_deg']} deg, {row['points_per_scan'][0] / 1e6:.2f} M points per scan), `forestreg batch --threads 1`, "
        f"{row['cores']} usable cores",
        f"{'workers':>7} {'wall s':>8} {'load 1-min before/after':>24} {'CPU s':>8} {'cores used':>10} {'plots at once':>13} {'ok':>6} {'plot s median (max)':>20} "
        f"{'plot CPU s median':>18} {'peak MB median (max)':>21} {'worst error deg / mm':>21}",
    ]
    for r in row["runs"]:
        e = r["error"]
        lines.append(
            f"{r['workers']:>7} {r['wall_s']:>8.1f} {r['load_before']:>11.2f} / {r['load_after']:<10.2f} {r['cpu_s']:>8.1f} "
            f"{r['cpu_s'] / r['wall_s']:>10.2f} {sum(r['plot_seconds']) / r['wall_s']:>13.2f} "
            f"{r['ok']:>3}/{r['plots']:<2} {statistics.median(r['plot_seconds']):>10.1f} ({max(r['plot_seconds']):.1f}) "
            f"{statistics.median(r['plot_cpu_s']):>18.1f} {statistics.median(r['plot_peak_mb']):>11.0f} ({max(r['plot_peak_mb']):.0f}) "
            f"{e['rotation_deg']:>11.3f} / {e['translation_m'] * 1000:.1f}"
            + (f", {e['unregistered']} unregistered" if e["unregistered"] else "")
        )
        if r["exit_code"]:
            lines.append(
                f"        exit status {r['exit_code']}: {r['stderr'].strip().splitlines()[-1] if r['stderr'].strip() else ''}"
            )
    lines.append(
        "speed-up with 2 workers (wall 1 / wall 2, per round): " + ", ".join(f"{s:.2f}x" for s in row["speedup"])
    )
    lines.append(
        "cores used: CPU time of the whole batch / its wall time (what the machine gave it); plots at once: the plots' "
        "wall times summed / the batch's (how busy the batch kept its workers)"
    )
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=1, help="rounds of (1 worker, 2 workers) (default 1)")
    ap.add_argument("--plots", type=int, default=20, help="plots in the batch (default 20)")
    ap.add_argument(
        "--workdir",
        type=Path,
        default=Path("bench_out"),
        help="where the plots are simulated (reused) and the batches write",
    )
    ap.add_argument("--json", type=Path, help="also write the row to this JSON file")
    args = ap.parse_args(argv)
    row = run(args.workdir, rounds=args.rounds, plots=args.plots)
    return peers.show_rows(format_row(row), row, args.json)


if __name__ == "__main__":
    sys.exit(main())
