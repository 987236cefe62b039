"""Benchmark: how a pair's time and memory grow with the scans' size -- forestreg against Sylva and
against reading the two files, at 1, 3, 10, 30 and 50 M points per scan (the sizes configurable).

The pairs share one simulated ``mixed_temperate`` plot (60 m side, scanners 12 m apart, 0.1 deg
angular step: about 3 M points per scan) and its true relative pose. A size below the simulated
scan's is a random subset of its points (in scan order); a size above it is the scan repeated with
millimetre jitter (every copy a fresh +-2 mm jitter of each coordinate) until the count is reached,
written chunk by chunk (the writer never holds the densified scan). Both scans of a pair have the
same count. The files are made once and kept in the work folder (reused by later runs).

At each size three commands run as child processes, in turn (read, forestreg, Sylva; ``--runs``
rounds), so that the machine's load hits all three alike:

* ``read``: a Python process that reads both LAZ files with forestreg's reader (the floor);
* ``forestreg``: ``python -m forestreg.cli register A B --out DIR --quiet``;
* ``sylva``: ``sylva coreg A B -o DIR --quiet`` (PyPI ``sylva-rs``), when installed.

Wall time is the clock around each child; peak memory is the larger of the kernel's accounting of
the finished child (``ru_maxrss``) and the largest sum of resident memory over the child's whole
process tree seen while it ran (sampled every 20 ms). Ratios are taken round by round (forestreg /
Sylva, forestreg / read, Sylva / read) and their median reported. Accuracy: each tool's matrix
against the simulator's truth (rotation error, degrees; translation error, millimetres).

Run from the repository root::

    python -m benchmarks.scaling                          # 1, 3, 10, 30, 50 M points per scan
    python -m benchmarks.scaling --sizes 0.1,1,3 --runs 3
    python -m benchmarks.run --only scaling [--quick]     # the launcher (--quick: 0.1, 0.3, 1 M)
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

if __package__:
    from . import peers
else:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import peers  # type: ignore[no-redef]

from forestreg.engine.core.transform import rigid_errors

#: Points per scan, millions: the table's sizes, and the --quick run's.
SIZES_M = (1.0, 3.0, 10.0, 30.0, 50.0)
QUICK_SIZES_M = (0.1, 0.3, 1.0)
#: The simulated pair every size is made from (label, preset, angular step deg, positions, seed).
BASE_PAIR = ("base", "mixed_temperate", 0.1, "-6,0;6,0", 3)
#: Default folder of the simulated and resized scans (kept between runs).
WORKDIR = Path("bench_out") / "scaling"
#: Jitter of each coordinate of a repeated copy, metres.
JITTER_M = 0.002


def resize(source: Path, target: Path, n_points: int, seed: int = 0, jitter_m: float = JITTER_M) -> int:
    """Write ``n_points`` points made from ``source``'s into ``target`` (LAZ, same header frame):
    fewer than the source has -- a random subset in scan order; more -- the source repeated, each
    copy jittered by up to ``jitter_m`` per coordinate, the last copy a random subset. Returns the
    count written."""
    import laspy

    rng = np.random.default_rng(seed)
    base, header = peers.read_laz_like(source)
    n_base = len(base.points)
    steps = np.round(jitter_m / base.header.scales).astype(np.int64)
    left = int(n_points)
    copy = 0
    tmp = target.with_name(target.name + ".part")
    with laspy.open(str(tmp), mode="w", header=header, do_compress=True) as writer:
        while left > 0:
            take = np.arange(n_base) if left >= n_base else np.sort(rng.choice(n_base, left, replace=False))
            chunk = laspy.ScaleAwarePointRecord.zeros(len(take), header=header)
            for name, step in zip(("X", "Y", "Z"), steps):
                values = np.asarray(base.points[name], dtype=np.int64)[take]
                if copy:  # the first copy is the scan itself
                    values = values + rng.integers(-step, step + 1, len(values))
                chunk[name] = values.astype(np.int32)
            if "intensity" in base.point_format.dimension_names:
                chunk["intensity"] = np.asarray(base.points["intensity"])[take]
            writer.write_points(chunk)
            left -= len(take)
            copy += 1
    tmp.replace(target)
    return int(n_points)


def make_pair(workdir: Path, size_m: float) -> tuple[Path, Path, np.ndarray]:
    """The pair of ``size_m`` million points per scan (made on first use): its two files and the
    true moving -> reference matrix."""
    label, preset, step, positions, seed = BASE_PAIR
    base = peers.simulate_pair(workdir, label, preset, step, positions, seed)
    truth, _ = peers._truth(base)
    n = int(round(size_m * 1e6))
    files = []
    for i, name in enumerate(("scan_01", "scan_02")):
        target = workdir / f"{n // 1000}k" / f"{name}.laz"
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            resize(base / f"{name}.laz", target, n, seed=i)
        files.append(target)
    return files[0], files[1], truth


def bench_size(workdir: Path, size_m: float, runs: int, sylva: Optional[str]) -> dict[str, Any]:
    """Time reading, forestreg and Sylva on the pair of ``size_m`` M points per scan, in turn."""
    a, b, truth = make_pair(workdir, size_m)
    out_f, out_s = a.parent / "out_forestreg", a.parent / "out_sylva"
    reader = "import sys\nfrom forestreg.engine.io import read_scan\nfor p in sys.argv[1:]:\n    read_scan(p)\n"
    commands = {
        "read": [sys.executable, "-c", reader, str(a), str(b)],
        "forestreg": [
            sys.executable,
            "-m",
            "forestreg.cli",
            "register",
            str(a),
            str(b),
            "--out",
            str(out_f),
            "--quiet",
        ],
    }
    if sylva:
        commands["sylva"] = [sylva, "coreg", str(a), str(b), "-o", str(out_s), "--quiet"]
    results: dict[str, list[peers.Run]] = {k: [] for k in commands}
    for _ in range(max(1, runs)):
        for name, argv in commands.items():
            own = {"forestreg": out_f, "sylva": out_s}.get(name)
            if own is not None and own.exists():
                shutil.rmtree(own)
            results[name].append(peers.run_command(argv, env=peers._python_env(), timeout_s=3600))
    row: dict[str, Any] = {"size_m": size_m, "points": int(round(size_m * 1e6)), "runs": max(1, runs)}
    for name, rs in results.items():
        row[name] = {
            "wall_s": statistics.median(r.wall_s for r in rs),
            "peak_mb": statistics.median(_peak(r) for r in rs),
            "status": sorted({r.status for r in rs}),
        }
    for num, den in (("forestreg", "read"), ("forestreg", "sylva"), ("sylva", "read")):
        if num in results and den in results:
            row[f"{num}/{den}"] = {
                "wall": statistics.median(x.wall_s / y.wall_s for x, y in zip(results[num], results[den])),
                "peak": statistics.median(_peak(x) / _peak(y) for x, y in zip(results[num], results[den])),
            }
    for name, matrix in (
        ("forestreg", peers._forestreg_matrix(out_f)),
        ("sylva", peers._sylva_matrix(out_s) if sylva else None),
    ):
        if name in row:
            row[name]["error"] = (
                None if matrix is None else dict(zip(("rotation_deg", "translation_m"), rigid_errors(matrix, truth)))
            )
    return row


def _peak(run: peers.Run) -> float:
    """A run's peak memory (MiB): the kernel's high-water mark of its largest process or the largest
    sum over its process tree seen while it ran, whichever is larger."""
    return float(np.fmax(run.peak_mb, run.tree_mb))


def run(sizes: Sequence[float] = SIZES_M, runs: int = 1, workdir: Optional[Path] = None) -> list[dict[str, Any]]:
    """One row per size (see the module's docstring)."""
    workdir = Path(workdir) if workdir is not None else WORKDIR
    workdir.mkdir(parents=True, exist_ok=True)
    sylva = peers.sylva_command()
    # untimed: the first command of a checkout compiles (or loads) its kernels
    a, b, _ = make_pair(workdir, min(sizes))
    warm = a.parent / "out_warm_up"
    peers.run_command(
        [sys.executable, "-m", "forestreg.cli", "register", str(a), str(b), "--out", str(warm), "--quiet"],
        env=peers._python_env(),
    )
    shutil.rmtree(warm, ignore_errors=True)
    rows = []
    for size in sizes:
        rows.append(bench_size(workdir, size, runs, sylva))
        print(format_rows(rows[-1:], head=len(rows) == 1), flush=True)
    return rows


def _error(e: Optional[dict[str, float]]) -> str:
    return "no result" if e is None else f"{e['rotation_deg']:.3f} deg / {1000 * e['translation_m']:.1f} mm"


def format_rows(rows: list[dict[str, Any]], head: bool = True) -> str:
    """The table (Markdown): per size, each command's wall time and peak memory, the ratios and the
    errors against the truth."""
    lines = []
    if head:
        lines += [
            "Pair at scale: both scans of N points (median of runs; ratios are medians of the round-by-round ratios)",
            "| points per scan | read s | forestreg s | Sylva s | forestreg / Sylva | forestreg / read | Sylva / read "
            "| read MB | forestreg MB | Sylva MB | forestreg / Sylva | forestreg error | Sylva error |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
        ]
    for r in rows:
        s = r.get("sylva")
        fs, fr, sr = r.get("forestreg/sylva"), r["forestreg/read"], r.get("sylva/read")
        bad = "" if r["forestreg"]["status"] == [0] else f" (exit {r['forestreg']['status']})"
        lines.append(
            f"| {r['size_m']:g} M | {r['read']['wall_s']:.1f} | {r['forestreg']['wall_s']:.1f}{bad} | "
            + (f"{s['wall_s']:.1f} | {fs['wall']:.2f} | " if s else "- | - | ")
            + f"{fr['wall']:.2f} | "
            + (f"{sr['wall']:.2f} | " if sr else "- | ")
            + f"{r['read']['peak_mb']:,.0f} | {r['forestreg']['peak_mb']:,.0f} | "
            + (f"{s['peak_mb']:,.0f} | {fs['peak']:.2f} | " if s else "- | - | ")
            + f"{_error(r['forestreg'].get('error'))} | "
            + (f"{_error(s.get('error'))} |" if s else "- |")
        )
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--sizes", default=",".join(f"{s:g}" for s in SIZES_M), help="points per scan, millions, comma-separated"
    )
    ap.add_argument("--quick", action="store_true", help=f"sizes {', '.join(f'{s:g}' for s in QUICK_SIZES_M)} M")
    ap.add_argument("--runs", type=int, default=1, help="rounds per size (default 1)")
    ap.add_argument("--workdir", type=Path, default=WORKDIR, help=f"the scans' folder (default {WORKDIR}; reused)")
    ap.add_argument("--json", type=Path, help="also write the rows to this JSON file")
    args = ap.parse_args(argv)
    sizes = QUICK_SIZES_M if args.quick else tuple(float(s) for s in args.sizes.split(","))
    rows = run(sizes, args.runs, args.workdir)
    print()
    return peers.show_rows(format_rows(rows), rows, args.json)


if __name__ == "__main__":
    sys.exit(main())
