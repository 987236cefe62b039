"""Benchmark: a plot of ten ~30 M-point scans (0.04 deg RIEGL-sized) registered with
``forestreg plot`` and merged out of core into one COPC file, against a 4 GB memory limit.

The plot is simulated at 0.1 deg (``forestreg simulate mixed_temperate``, an 80 m plot, about
3.1 M points a scan): a centre scan at (0, 0) and the others evenly on a ring 12 m around it
(:func:`plot_positions`), as a surveyor places them. Each scan is then densified to ~30 M points
(:func:`benchmarks.big_scan.densify`: ten copies with millimetre jitter, in the scan's own file
coordinates, so the simulator's truth still holds). One child process runs::

    forestreg plot S01 ... S10 --out DIR --merged DIR.copc.laz --quiet

(each scan linked to the centre scan, the report, the merged COPC file); its wall time comes from
the parent's clock and its peak resident memory from the operating system (``os.wait4``
``ru_maxrss``, :func:`benchmarks.peers.run_command`).

Memory is judged against the 4 GB limit and against a budget of 3x the raw point arrays
(float64 x, y, z) of the *largest* scan + 300 MB: a plot run holds scans a link at a time and
streams the merged output, so its memory should follow its largest scan, not the plot's total
(ten 30 M-point scans are 7.5 GB of raw arrays). Accuracy: each scan's pose (its file coordinates
-> the centre scan's) against the truth, rotation in degrees and translation in millimetres. The
merged file's point count (its LAS header, read with laspy) is checked against the sum of the
registered inputs.

The simulated and densified scans are kept under ``--workdir`` and reused (default
``bench_out/``); about 170 MB of LAZ per 30 M-point scan, plus the COPC spill files while merging
(16 bytes a point, ~5 GB for the plot). Run (about an hour on 2 cores at full size)::

    python -m benchmarks.big_plot [--scans 10] [--copies 10] [--workdir DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any, Optional

import numpy as np

if __package__:
    from . import big_scan, peers
else:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import big_scan  # type: ignore[no-redef]
    import peers  # type: ignore[no-redef]

from forestreg.engine.core.transform import rigid_errors

PRESET = "mixed_temperate"
STEP_DEG = 0.1
SIZE_M = 80.0
RING_M = 12.0
SEED = 3
#: The 4 GB memory limit, MB.
LIMIT_MB = 4096.0


def plot_positions(n_scans: int, ring_m: float = RING_M) -> list[tuple[float, float]]:
    """Scanner positions (x, y metres, the plot's frame): the centre scan at the origin and the
    other ``n_scans - 1`` evenly on a circle of radius ``ring_m`` around it, the first at +x."""
    ring = [(ring_m * math.cos(2 * math.pi * k / (n_scans - 1)), ring_m * math.sin(2 * math.pi * k / (n_scans - 1))) for k in range(n_scans - 1)]
    return [(0.0, 0.0)] + [(round(x, 2), round(y, 2)) for x, y in ring]


def simulate(workdir: Path, n_scans: int) -> Path:
    """The simulated plot (``scan_XX.laz`` + ``truth.json``) under ``workdir``; simulated only
    when missing."""
    out = workdir / f"plot{n_scans}_{PRESET}_{STEP_DEG}_{SEED}"
    if not (out / "truth.json").exists():
        positions = ";".join(f"{x:g},{y:g}" for x, y in plot_positions(n_scans))
        subprocess.run(
            [sys.executable, "-m", "forestreg.cli", "simulate", PRESET, "--out", str(out), f"--positions={positions}",
             "--step", str(STEP_DEG), "--size", str(SIZE_M), "--seed", str(SEED), "--quiet"],
            check=True, stdout=subprocess.DEVNULL, env=peers._python_env(),
        )
    return out


def densified(plot: Path, copies: int) -> list[Path]:
    """Each scan of the simulated plot densified ``copies`` times (same file name, in
    ``plot/dense_x<copies>/``); a scan already there is reused (written under a temporary name and
    renamed, so an interrupted run leaves no partial scan)."""
    names = [s["file"] for s in json.loads((plot / "truth.json").read_text())["scans"]]
    folder = plot / f"dense_x{copies}"
    folder.mkdir(exist_ok=True)
    paths = []
    for k, name in enumerate(names):
        target = folder / name
        if not target.exists():
            partial = folder / f".partial-{name}"
            big_scan.densify(plot / name, partial, copies, seed=k)
            partial.replace(target)
        paths.append(target)
    return paths


def _truth(plot: Path) -> dict[str, np.ndarray]:
    """Each scan's true pose relative to the first (centre) scan: its file -> the centre's file."""
    scans = json.loads((plot / "truth.json").read_text())["scans"]
    first = np.linalg.inv(np.array(scans[0]["matrix"], dtype=float))
    return {Path(s["file"]).stem: first @ np.array(s["matrix"], dtype=float) for s in scans}


def _poses(out: Path) -> dict[str, Optional[np.ndarray]]:
    """The poses ``forestreg plot`` wrote (``poses.json``), by scan file stem; {} when missing."""
    try:
        scans = json.loads((out / "poses.json").read_text())["scans"]
    except (OSError, ValueError, KeyError):
        return {}
    return {Path(k).stem: (None if v.get("matrix") is None else np.array(v["matrix"], dtype=float)) for k, v in scans.items()}


def _point_count(path: Path) -> Optional[int]:
    """The point count in a LAS/LAZ/COPC header (laspy), None when the file is missing or unreadable."""
    import laspy

    try:
        with laspy.open(str(path)) as f:
            return int(f.header.point_count)
    except (OSError, ValueError, laspy.errors.LaspyException):
        return None


def run(scans: int = 10, copies: int = 10, workdir: Optional[Path] = None, *, timeout_s: float = 4 * 3600.0) -> dict[str, Any]:
    """Simulate and densify the plot (or reuse it), register it with the merged COPC output in a
    child process, and return the row: points, wall s, peak MB, budgets, per-scan errors, counts."""
    if scans < 2:
        raise ValueError("a plot needs at least two scans")
    base = Path(workdir) if workdir is not None else Path("bench_out")
    base.mkdir(parents=True, exist_ok=True)
    plot = simulate(base, scans)
    files = densified(plot, copies)
    points = [_point_count(p) or 0 for p in files]
    out, merged = plot / f"out_x{copies}", plot / f"merged_x{copies}.copc.laz"
    if out.exists():
        shutil.rmtree(out)
    merged.unlink(missing_ok=True)
    argv = [sys.executable, "-m", "forestreg.cli", "plot", *map(str, files), "--out", str(out), "--merged", str(merged), "--quiet"]
    log = plot / f"big_plot_x{copies}.log"
    result = peers.run_command(argv, env=peers._python_env(), timeout_s=timeout_s, log=log)
    truth, poses = _truth(plot), _poses(out)
    errors: dict[str, Optional[dict[str, float]]] = {}
    for path in files[1:]:
        pose = poses.get(path.stem)
        errors[path.stem] = None if pose is None else dict(zip(("rotation_deg", "translation_m"), rigid_errors(pose, truth[path.stem])))
    registered = [n for p, n in zip(files, points) if poses.get(p.stem) is not None]
    raw_mb = max(points) * 3 * 8 / 1e6
    return {
        "scans": scans,
        "copies": copies,
        "points": points,
        "total_points": sum(points),
        "raw_mb_largest": raw_mb,
        "budget_mb": 3 * raw_mb + 300,
        "limit_mb": LIMIT_MB,
        "wall_s": result.wall_s,
        "peak_mb": result.peak_mb,
        "status": result.status,
        "log": str(log),
        "errors": errors,
        "merged_points": _point_count(merged),
        "registered_points": sum(registered),
    }


def _error_text(error: Optional[dict[str, float]]) -> str:
    return "not registered" if error is None else f"{error['rotation_deg']:.4f} / {1000 * error['translation_m']:.1f}"


def format_row(row: dict[str, Any]) -> str:
    """The table of one run: size, wall, peak memory against both budgets, errors, merged count."""
    errs = [e for e in row["errors"].values() if e is not None]
    missing = [k for k, e in row["errors"].items() if e is None]
    lines = [
        f"Big plot: {row['scans']} scans x ~{np.mean(row['points']) / 1e6:.1f} M points (0.1 deg scans densified x{row['copies']}), "
        f"forestreg plot --merged OUT.copc.laz",
        f"{'scans':>6} {'points':>10} {'wall s':>8} {'peak MB':>8} {'/4 GB':>6} {'/budget':>8} {'worst deg':>10} {'worst mm':>9} {'merged':>12} {'inputs':>12}",
        "-" * 98,
        f"{row['scans']:>6} {row['total_points'] / 1e6:>9.1f}M {row['wall_s']:>8.0f} {row['peak_mb']:>8.0f} "
        f"{row['peak_mb'] / row['limit_mb']:>6.2f} {row['peak_mb'] / row['budget_mb']:>8.2f} "
        + (f"{max(e['rotation_deg'] for e in errs):>10.4f} {1000 * max(e['translation_m'] for e in errs):>9.1f} " if errs else f"{'-':>10} {'-':>9} ")
        + f"{row['merged_points'] if row['merged_points'] is not None else 'none':>12} {row['registered_points']:>12}",
        f"budget: 3x the raw arrays of the largest scan ({row['raw_mb_largest']:.0f} MB) + 300 = {row['budget_mb']:.0f} MB; "
        f"limit {row['limit_mb']:.0f} MB; exit {row['status']}"
        + ("" if row["status"] == 0 else f" (log: {row['log']})"),
        "per scan (rotation deg / translation mm vs truth): " + ", ".join(f"{k} {_error_text(e)}" for k, e in row["errors"].items()),
    ]
    if row["merged_points"] is not None and row["merged_points"] != row["registered_points"]:
        lines.append(f"MISMATCH: the merged file holds {row['merged_points']} points, the registered scans {row['registered_points']}")
    if missing:
        lines.append(f"not registered: {', '.join(missing)}")
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description="forestreg plot with a merged COPC output on ten ~30 M-point scans: wall, peak memory, accuracy")
    ap.add_argument("--scans", type=int, default=10, help="scans in the plot: a centre scan and the rest on a 12 m ring (default 10)")
    ap.add_argument("--copies", type=int, default=10, help="copies of each 0.1 deg scan (~3.1 M points) in its dense scan (default 10: ~31 M)")
    ap.add_argument("--workdir", type=Path, help="keep the simulated and densified scans here (default bench_out/; reused when present)")
    ap.add_argument("--json", type=Path, help="also write the row to this JSON file")
    args = ap.parse_args()
    row = run(args.scans, args.copies, args.workdir)
    peers.show_rows(format_row(row), row, args.json)
