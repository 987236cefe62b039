"""Benchmark: peak memory of System B's commands against their memory budget, each command a
child process (``forestreg coregister``, ``forestreg fuse``, ``forestreg trees``).

The budget of a command is 3x its raw point arrays (float64 x, y, z of every input point, 24 bytes
a point) plus 300 MB. The cases are the other System B benchmarks' (cached under ``bench_out/``,
simulated when missing): the backpack (3.4 M points) and UAV (0.4 M) clouds of
:mod:`benchmarks.coreg_speed` for ``coregister`` and ``fuse`` (the transform is the one
``coregister`` just wrote), and the 2.9 M-point TLS plot of :mod:`benchmarks.trees_speed` for
``trees``; and ``trees`` on each real cloud of ``../shared/data`` (:data:`REAL_CLOUDS`, those
present: TLS, MLS, ALS and ULS). Peak memory is the kernel's accounting of the finished child (``os.wait4``
``ru_maxrss``, KiB), printed in MB (10^6 bytes) like the budget; wall time from the parent's clock.
Each command runs ``--runs`` times; the table has the medians. Nothing is asserted.

Run from the repository root: ``python -m benchmarks.command_memory [--runs 3] [--json FILE]``.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Optional

if __package__:
    from . import coreg_speed, peers, trees_speed
else:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import coreg_speed  # type: ignore[no-redef]
    import peers  # type: ignore[no-redef]
    import trees_speed  # type: ignore[no-redef]

#: Bytes of the raw point arrays a point (float64 x, y, z).
RAW_BYTES_PER_POINT = 24
#: The budget's allowance beyond 3x the raw arrays, MB.
BUDGET_ALLOWANCE_MB = 300.0
#: The real clouds (beside the repository, as the tests find them) measured with ``trees``.
REAL_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
REAL_CLOUDS = (
    "LPine1_demo",
    "spanner_MLS_Clip",
    "pine_plot",
    "TLS_scan_scanner_at_origin",
    "spanner_ALS_Clip",
    "lidR_MixedConifer",
)


def _points_in(path: Path) -> int:
    import laspy

    with laspy.open(str(path)) as reader:
        return int(reader.header.point_count)


def _measure(name: str, argv: list[str], points: int, runs: int) -> dict[str, Any]:
    results = [peers.run_command(argv, env=peers._python_env(), timeout_s=1800) for _ in range(max(1, runs))]
    raw_mb = points * RAW_BYTES_PER_POINT / 1e6
    budget_mb = 3.0 * raw_mb + BUDGET_ALLOWANCE_MB
    peak_mb = statistics.median(r.peak_mb * 1024.0 * 1024.0 / 1e6 for r in results)  # run_command's MiB -> MB
    return {
        "command": name,
        "points": points,
        "raw_mb": raw_mb,
        "budget_mb": budget_mb,
        "peak_mb": peak_mb,
        "peak_over_budget": peak_mb / budget_mb,
        "wall_s": statistics.median(r.wall_s for r in results),
        "status": [r.status for r in results],
    }


def run(runs: int = 3, workdir: Optional[Path] = None) -> list[dict[str, Any]]:
    """One row a command (see the module's docstring)."""
    # the cases are simulated (first use) or read in a child process: read here, they grew this
    # process to ~430 MB, which the kernel then counted in the peak of every command and peer
    # started after them (a child's ru_maxrss includes its parent's memory at the fork)
    subprocess.run(
        [
            sys.executable,
            "-c",
            "from benchmarks import coreg_speed, trees_speed; "
            "coreg_speed.load_case('backpack'); trees_speed.load_case()",
        ],
        cwd=Path(__file__).resolve().parent.parent,
        check=True,
    )
    folder = coreg_speed.CACHE / "backpack_seed0"
    ground, uav, plot = folder / "ground.laz", folder / "uav.laz", trees_speed.OUT / "plot.laz"
    n_coreg = _points_in(ground) + _points_in(uav)
    exe = [sys.executable, "-m", "forestreg.cli"]
    rows = []
    with tempfile.TemporaryDirectory(prefix="forestreg-cmdmem-", dir=workdir) as tmp:
        out = Path(tmp)
        rows.append(
            _measure(
                "coregister",
                exe + ["coregister", str(ground), str(uav), "--out", str(out / "coreg"), "--quiet"],
                n_coreg,
                runs,
            )
        )
        transform = out / "coreg" / "transform.txt"
        rows.append(
            _measure(
                "fuse",
                exe
                + [
                    "fuse",
                    str(ground),
                    str(uav),
                    "--transform",
                    str(transform),
                    "--out",
                    str(out / "fused.laz"),
                    "--quiet",
                ],
                n_coreg,
                runs,
            )
        )
        rows.append(
            _measure(
                "trees", exe + ["trees", str(plot), "--out", str(out / "trees"), "--quiet"], _points_in(plot), runs
            )
        )
        for name in REAL_CLOUDS:
            cloud = REAL_DATA / f"{name}.laz"
            if cloud.exists():
                rows.append(
                    _measure(
                        f"trees {name}",
                        exe + ["trees", str(cloud), "--out", str(out / name), "--quiet"],
                        _points_in(cloud),
                        runs,
                    )
                )
    return rows


def format_rows(rows: list[dict[str, Any]]) -> str:
    head = "| command | points | raw arrays MB | budget MB (3x raw + 300) | peak MB | peak / budget | wall s | exit |"
    lines = ["Peak memory of System B's commands (median of runs)", head, "|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(
            f"| {r['command']} | {r['points'] / 1e6:.2f} M | {r['raw_mb']:.0f} | {r['budget_mb']:.0f} | {r['peak_mb']:,.0f} | "
            f"{r['peak_over_budget']:.2f} | {r['wall_s']:.1f} | {','.join(str(s) for s in r['status'])} |"
        )
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3, help="runs of each command (default 3; medians)")
    ap.add_argument("--json", type=Path, help="also write the rows to this JSON file")
    args = ap.parse_args(argv)
    rows = run(args.runs)
    return peers.show_rows(format_rows(rows), rows, args.json)


if __name__ == "__main__":
    sys.exit(main())
