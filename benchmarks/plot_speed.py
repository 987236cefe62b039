"""Benchmark: a 4-scan plot, every pair registered -- ``forestreg plot --pairs all`` vs Sylva.

The plot: a simulated ``mixed_temperate`` plot scanned from four positions on a 12 m square at
0.1 deg (about 3.1 M points per scan), simulated once with ``forestreg simulate`` and kept under
``--workdir``. Three whole commands run as child processes, in turn (read, forestreg, Sylva, read,
...), as in :mod:`benchmarks.peers`:

* ``read``: a Python process that reads the four LAZ files with forestreg's reader;
* ``forestreg``: ``forestreg plot S1 S2 S3 S4 --pairs all --out DIR --quiet`` (all six pairs, a
  pose graph weighted by each pair's evidence, the HTML report with its figures);
* ``sylva``: ``sylva coreg S1 S2 S3 S4 -o DIR --quiet`` (its multi-scan registration), when
  installed.

Wall time from the parent's clock, peak memory from ``ru_maxrss`` of the finished child; ratios
are medians of the round-by-round ratios. Accuracy: every scan's pose relative to the first scan
against the simulator's truth (largest rotation and translation error over the scans).

Run: ``python -m benchmarks.plot_speed [--runs N] [--workdir DIR]`` (about 5 minutes per round).
"""

from __future__ import annotations

import json
import shutil
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any, Optional

import numpy as np

try:
    from .peers import Run, _python_env, run_command, sylva_command
except ImportError:  # run as a script
    from peers import Run, _python_env, run_command, sylva_command  # type: ignore[no-redef]

from forestreg.engine.core.transform import rigid_errors

POSITIONS = "-6,-6;6,-6;6,6;-6,6"
NAMES = ("scan_01", "scan_02", "scan_03", "scan_04")


def simulate(workdir: Path, step_deg: float = 0.1, seed: int = 3) -> Path:
    """The four scans and truth.json (simulated when missing)."""
    out = workdir / f"plot4_{step_deg}_{seed}"
    if not (out / "truth.json").exists():
        subprocess.run(
            [
                sys.executable,
                "-m",
                "forestreg.cli",
                "simulate",
                "mixed_temperate",
                "--out",
                str(out),
                f"--positions={POSITIONS}",
                "--step",
                str(step_deg),
                "--seed",
                str(seed),
                "--quiet",
            ],
            check=True,
            stdout=subprocess.DEVNULL,
            env=_python_env(),
        )
    return out


def _truth(folder: Path) -> dict[str, np.ndarray]:
    """Each scan's true pose relative to the first scan (file -> first scan's file coordinates)."""
    scans = json.loads((folder / "truth.json").read_text())["scans"]
    first = np.linalg.inv(np.array(scans[0]["matrix"], dtype=float))
    return {s["name"]: first @ np.array(s["matrix"], dtype=float) for s in scans}


def _forestreg_poses(out: Path) -> dict[str, Optional[np.ndarray]]:
    try:
        poses = json.loads((out / "poses.json").read_text())["scans"]
    except (OSError, ValueError, KeyError):
        return {}
    return {
        Path(k).stem: (np.array(v["matrix"], dtype=float) if v.get("matrix") is not None else None)
        for k, v in poses.items()
    }


def _sylva_poses(out: Path) -> dict[str, Optional[np.ndarray]]:
    try:
        scans = json.loads((out / "transforms.json").read_text()).get("scans", [])
    except (OSError, ValueError):
        return {}
    world = {int(s["index"]): np.array(s["world_from_scan"], dtype=float) for s in scans if s.get("registered")}
    if 0 not in world:
        return {}
    return {NAMES[i]: np.linalg.inv(world[0]) @ m for i, m in world.items() if i < len(NAMES)}


def _worst_error(poses: dict[str, Optional[np.ndarray]], truth: dict[str, np.ndarray]) -> Optional[dict[str, float]]:
    errors = []
    for name in NAMES[1:]:
        if poses.get(name) is None:
            return None
        errors.append(rigid_errors(poses[name], truth[name]))
    return {"rotation_deg": max(e[0] for e in errors), "translation_m": max(e[1] for e in errors)}


def bench(folder: Path, runs: int, sylva: Optional[str]) -> dict[str, Any]:
    """Time the commands on the plot, ``runs`` rounds (no warm-up round: each takes minutes)."""
    files = [str(folder / f"{n}.laz") for n in NAMES]
    out_f, out_s = folder / "out_forestreg", folder / "out_sylva"
    reader = "import sys\nfrom forestreg.engine.io import read_scan\nfor p in sys.argv[1:]:\n    read_scan(p)\n"
    commands = {
        "read": [sys.executable, "-c", reader, *files],
        "forestreg": [
            sys.executable,
            "-m",
            "forestreg.cli",
            "plot",
            *files,
            "--pairs",
            "all",
            "--out",
            str(out_f),
            "--quiet",
        ],
    }
    if sylva:
        commands["sylva"] = [sylva, "coreg", *files, "-o", str(out_s), "--quiet"]
    results: dict[str, list[Run]] = {k: [] for k in commands}
    for _ in range(runs):
        for name, argv in commands.items():
            own = {"forestreg": out_f, "sylva": out_s}.get(name)
            if own is not None and own.exists():
                shutil.rmtree(own)
            results[name].append(run_command(argv, env=_python_env(), timeout_s=3600.0))
    truth = _truth(folder)
    points = [int(s["n_points"]) for s in json.loads((folder / "truth.json").read_text())["scans"]]
    row: dict[str, Any] = {"points": points, "runs": runs, "raw_mb": sum(points) * 3 * 8 / 1e6}
    for name, rs in results.items():
        row[name] = {
            "wall_s": statistics.median(r.wall_s for r in rs),
            "peak_mb": statistics.median(r.peak_mb for r in rs),
            "status": sorted({r.status for r in rs}),
        }
    for other in [k for k in commands if k != "forestreg"]:
        row[f"forestreg/{other}"] = {
            "wall": statistics.median(f.wall_s / o.wall_s for f, o in zip(results["forestreg"], results[other])),
            "peak": statistics.median(f.peak_mb / o.peak_mb for f, o in zip(results["forestreg"], results[other])),
        }
    row["forestreg"]["error"] = _worst_error(_forestreg_poses(out_f), truth)
    if sylva:
        row["sylva"]["error"] = _worst_error(_sylva_poses(out_s), truth)
    return row


def format_row(row: dict[str, Any]) -> str:
    """The table of one plot: wall, peak memory, ratios, worst pose error of each tool."""
    has_sylva = "sylva" in row
    lines = [
        f"4-scan plot, every pair ({' + '.join(f'{p / 1e6:.2f}' for p in row['points'])} M points), median of {row['runs']} rounds"
    ]
    head = (
        f"{'':>10} {'read':>9} {'forestreg':>10}"
        + (f" {'Sylva':>9}" if has_sylva else "")
        + f" {'fr/read':>8}"
        + (f" {'fr/Sylva':>9}" if has_sylva else "")
    )
    lines += [head, "-" * len(head)]
    for what, key, fmt in (("wall s", "wall_s", "{:.1f}"), ("peak MB", "peak_mb", "{:.0f}")):
        ratio = "wall" if key == "wall_s" else "peak"
        lines.append(
            f"{what:>10} {fmt.format(row['read'][key]):>9} {fmt.format(row['forestreg'][key]):>10}"
            + (f" {fmt.format(row['sylva'][key]):>9}" if has_sylva else "")
            + f" {row['forestreg/read'][ratio]:>8.2f}"
            + (f" {row['forestreg/sylva'][ratio]:>9.2f}" if has_sylva else "")
        )
    budget = 3 * row["raw_mb"] + 300
    lines.append(
        f"raw point arrays {row['raw_mb']:.0f} MB: memory budget 3x + 300 = {budget:.0f} MB, forestreg {row['forestreg']['peak_mb'] / budget:.2f} of it"
    )
    errs = []
    for name in ("forestreg", "sylva"):
        if name in row:
            e = row[name].get("error")
            errs.append(
                f"{name} "
                + (
                    "not every scan registered"
                    if e is None
                    else f"{e['rotation_deg']:.4f} deg / {1000 * e['translation_m']:.1f} mm"
                )
            )
    lines.append("worst pose error vs truth: " + ", ".join(errs))
    if not has_sylva:
        lines.append("Sylva not installed (pip install 'forestreg[bench]'): its columns are left out")
    return "\n".join(lines)


def run(*, runs: int = 2, workdir: Optional[Path] = None) -> dict[str, Any]:
    base = Path(workdir) if workdir is not None else Path("bench_out")
    base.mkdir(parents=True, exist_ok=True)
    return bench(simulate(base), runs, sylva_command())


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="forestreg plot --pairs all vs Sylva coreg on a simulated 4-scan plot")
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument(
        "--workdir", type=Path, help="keep the simulated plot here (default bench_out/; reused when present)"
    )
    args = ap.parse_args()
    print(format_row(run(runs=args.runs, workdir=args.workdir)))
