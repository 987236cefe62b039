"""Benchmark: peak memory of ``forestreg register`` on a ~30 M-point scan (a 0.04 deg RIEGL-sized
scan) against the memory budget (3x the raw point arrays + 300 MB, and 4 GB).

The big reference scan is synthetic: a simulated 0.1 deg scan (about 3 M points) repeated ten
times with millimetre jitter, written chunk by chunk (the writer never holds the 30 M points);
the moving scan is the simulated pair's other scan. The command runs as a child process; its peak
resident memory is the operating system's accounting (``os.wait4``). Run::

    python benchmarks/big_scan.py [--copies 10] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any, Optional

import numpy as np

if __package__:
    from . import peers
else:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import peers  # type: ignore[no-redef]

from forestreg.engine.core.transform import rigid_errors


def densify(source: Path, target: Path, copies: int, jitter_m: float = 0.002, seed: int = 0) -> int:
    """Write ``copies`` jittered copies of ``source``'s points into ``target`` (LAZ), one copy at a
    time; returns the point count written."""
    import laspy

    rng = np.random.default_rng(seed)
    base, header = peers.read_laz_like(source)
    total = 0
    with laspy.open(str(target), mode="w", header=header, do_compress=True) as writer:
        for _ in range(copies):
            chunk = laspy.ScaleAwarePointRecord.zeros(len(base.points), header=header)
            steps = np.round(jitter_m / base.header.scales).astype(np.int64)
            for name, step in zip(("X", "Y", "Z"), steps):
                values = np.asarray(base.points[name], dtype=np.int64)
                chunk[name] = (values + rng.integers(-step, step + 1, len(values))).astype(np.int32)
            if "intensity" in base.point_format.dimension_names:
                chunk["intensity"] = base.points["intensity"]
            writer.write_points(chunk)
            total += len(chunk)
    return total


def run(copies: int = 10, workdir: Optional[Path] = None) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="forestreg-big-") as tmp:
        base = Path(workdir) if workdir is not None else Path(tmp)
        pair = peers.simulate_pair(base, "big", "mixed_temperate", 0.1, "-6,0;6,0", 3)
        big = pair / f"scan_01_x{copies}.laz"
        if not big.exists():
            densify(pair / "scan_01.laz", big, copies)
        truth, points = peers._truth(pair)
        n_big = points[0] * copies
        out = pair / "out_big"
        argv = [
            sys.executable,
            "-m",
            "forestreg.cli",
            "register",
            str(big),
            str(pair / "scan_02.laz"),
            "--out",
            str(out),
            "--quiet",
        ]
        result = peers.run_command(argv, env=peers._python_env(), timeout_s=3600)
        raw_mb = (n_big + points[1]) * 3 * 8 / 1e6
        matrix = peers._forestreg_matrix(out)
        row = {
            "points": [n_big, points[1]],
            "raw_mb": raw_mb,
            "budget_mb": 3 * raw_mb + 300,
            "wall_s": result.wall_s,
            "peak_mb": result.peak_mb,
            "status": result.status,
            "error": None
            if matrix is None
            else dict(zip(("rotation_deg", "translation_m"), rigid_errors(matrix, truth))),
        }
        return row


def format_row(row: dict[str, Any]) -> str:
    e = row["error"]
    return (
        f"Big scan: {row['points'][0] / 1e6:.1f} M + {row['points'][1] / 1e6:.1f} M points, raw arrays {row['raw_mb']:.0f} MB; "
        f"peak {row['peak_mb']:.0f} MB = {row['peak_mb'] / row['budget_mb']:.2f} of the budget "
        f"(3x raw + 300 MB = {row['budget_mb']:.0f} MB; limit 4096 MB); wall {row['wall_s']:.0f} s; exit {row['status']}; "
        + (
            "no result"
            if e is None
            else f"error vs truth {e['rotation_deg']:.4f} deg / {1000 * e['translation_m']:.1f} mm"
        )
    )


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description="peak memory of forestreg register on a ~30 M-point scan")
    ap.add_argument("--copies", type=int, default=10)
    ap.add_argument("--workdir", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    row = run(args.copies, args.workdir)
    peers.show_rows(format_row(row), row, args.json)
