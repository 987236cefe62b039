"""Benchmark: whole commands side by side -- reading the files, ``forestreg register``, Sylva.

Each pair of scans is simulated once (``forestreg simulate``: LAZ files plus the truth), then three
commands run as child processes, in turn (read, forestreg, Sylva, read, forestreg, Sylva, ...), so
that a drift of the machine's speed (other users) hits all three alike:

* ``read``: a Python process that reads both LAZ files with forestreg's reader (the floor: what
  any tool pays to decode the files);
* ``forestreg``: ``python -m forestreg.cli register A B --out DIR --quiet``;
* ``sylva``: ``sylva coreg A B -o DIR --quiet`` (PyPI ``sylva-rs``, the ``bench`` extra), when
  installed.

Wall time comes from the clock around each child, peak memory from the operating system's
accounting of the finished child (``os.wait4`` ``ru_maxrss``: every resident page, the shared
libraries' code included; each command is started by a small launcher process, so that the
benchmark's own memory does not count into it, :data:`_LAUNCHER`); beside it, the largest
anonymous and file-backed parts seen while the child ran (``/proc/PID/status`` every 20 ms,
:func:`_resident_parts`). Ratios are taken run by run (forestreg / Sylva and forestreg / read of
the same round) and their median is reported, so they hold when the machine's load changes
between rounds; the absolute seconds do not.
Accuracy: each tool's matrix against the simulator's truth.

A third, tiny pair (:data:`FLOOR_PAIR`, left out by ``--quick``) measures the runtime's floor: what
``forestreg register`` holds whatever the scans (the interpreter and its libraries, numba's LLVM
library and kernels, the figure), set beside Sylva's peak on the largest pair.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from forestreg.engine.core.transform import rigid_errors

#: (label, preset, angular step deg, scanner positions, seed): the pairs of the table.
PAIRS = (
    ("0.45 M + 0.5 M points (0.25 deg)", "mixed_temperate", 0.25, "-6,0;6,0", 3),
    ("3.0 M + 3.1 M points (0.1 deg)", "mixed_temperate", 0.1, "-6,0;6,0", 3),
)
QUICK_PAIRS = PAIRS[:1]
#: A pair small enough that its points weigh nothing next to the runtime: ``forestreg register``'s
#: peak memory on it is the floor under any pair's (Python, NumPy, SciPy, numba with its LLVM
#: library and loaded kernels, the figure), set beside Sylva's peak on the largest pair.
FLOOR_PAIR = ("0.12 M + 0.12 M points (0.5 deg)", "mixed_temperate", 0.5, "-6,0;6,0", 3)


def show_rows(text: str, rows: Any, json_path: Optional[Path], **dump: Any) -> int:
    """Print a benchmark's table ``text`` and, with ``json_path``, keep its ``rows`` there as JSON
    (``dump``: options of ``json.dumps``; indent 2 unless given). Returns the exit code, 0."""
    print(text)
    if json_path:
        json_path.write_text(json.dumps(rows, **{"indent": 2, **dump}) + "\n")
    return 0


def read_laz_like(source: Path) -> tuple[Any, Any]:
    """The points of the LAS/LAZ file ``source`` and a new header in its point format, version,
    offsets and scales: points written under it stay in the source's frame and resolution."""
    import laspy

    with laspy.open(str(source)) as reader:
        base = reader.read()
    header = laspy.LasHeader(point_format=base.header.point_format, version=base.header.version)
    header.offsets = base.header.offsets
    header.scales = base.header.scales
    return base, header


@dataclass
class Run:
    """One finished child process: wall seconds, peak resident memory (MB), exit status, and the
    largest anonymous and file-backed parts of its resident memory seen while it ran (MB, sampled
    every 20 ms from ``/proc``; NaN where there is no ``/proc``)."""

    wall_s: float
    peak_mb: float
    status: int
    anon_mb: float = float("nan")
    file_mb: float = float("nan")
    tree_mb: float = float("nan")
    """The largest sum of resident memory over the command's whole process tree seen while it ran
    (MiB, sampled every 20 ms; NaN where there is no ``/proc``)."""


def _resident_parts(pid: int) -> tuple[float, float]:
    """(anonymous, file-backed) resident memory of process ``pid`` now, MiB; NaN when unknown.
    File-backed pages are mostly shared library code: how many the kernel maps into a process
    depends on how the library's pages sit in the page cache (on this project's machine,
    ``import llvmlite.binding`` took 117 MB or 56 MB of resident memory, the same file before and
    after it was dropped from the cache and read back), so the anonymous part is the steadier
    measure of what a run itself allocates."""
    anon = file_ = float("nan")
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("RssAnon:"):
                    anon = int(line.split()[1]) / 1024.0
                elif line.startswith("RssFile:"):
                    file_ = int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return anon, file_


#: A small Python process that starts the measured command as its own child, waits for it and
#: writes its wall time (from the fork to its end), ``ru_maxrss`` (KiB) and wait status to the
#: file ``argv[1]``: the command is forked from this interpreter of ~10 MB, not from the benchmark
#: process, whose resident memory at the fork the kernel would count into the command's peak (it
#: keeps the larger of the two across ``exec``).
_LAUNCHER = """
import json, os, sys, time
t0 = time.perf_counter()
pid = os.fork()
if pid == 0:
    try:
        os.execvp(sys.argv[2], sys.argv[2:])
    finally:
        os._exit(127)
_, status, usage = os.wait4(pid, 0)
wall = time.perf_counter() - t0
with open(sys.argv[1], "w") as f:
    json.dump({"wall_s": wall, "maxrss_kib": usage.ru_maxrss, "status": status}, f)
"""


def _tree_rss_mb(pid: int) -> float:
    """Resident memory summed over process ``pid`` and all its descendants now, MiB (NaN when
    unknown)."""
    total, seen, todo = 0.0, set(), [pid]
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            with open(f"/proc/{p}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1]) / 1024.0
                        break
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
    return total if seen else float("nan")


def run_command(
    argv: list[str],
    *,
    env: Optional[dict[str, str]] = None,
    timeout_s: float = 1800.0,
    log: Optional[Path] = None,
    kill_when: Optional[Callable[[], bool]] = None,
) -> Run:
    """Run ``argv`` to completion; its wall time and the peak memory the kernel accounted to it.
    Its output is dropped, or written to ``log`` (stdout and stderr) when given.

    The command runs under :data:`_LAUNCHER` (its own session: a timeout ends it and its
    children), so its peak is its own whatever the size of the calling process. Its anonymous
    and file-backed memory are sampled every 20 ms meanwhile (:func:`_resident_parts`).
    ``kill_when``: asked every 20 ms; once it answers True the command and its children are
    killed with SIGKILL (a crash, or ``kill -9``, mid-run) and the run's status is -9."""
    fd, report_name = tempfile.mkstemp(prefix="forestreg-run-", suffix=".json")
    os.close(fd)
    report = Path(report_name)
    sink = subprocess.DEVNULL if log is None else open(log, "wb")
    try:
        launcher = subprocess.Popen(
            [sys.executable, "-c", _LAUNCHER, str(report), *argv],
            stdout=sink,
            stderr=subprocess.STDOUT if log is not None else subprocess.DEVNULL,
            env=env,
            start_new_session=True,
        )
    finally:
        if log is not None:
            sink.close()
    deadline = time.perf_counter() + timeout_s
    anon_mb = file_mb = tree_mb = float("nan")
    child = None
    try:
        while launcher.poll() is None:
            if child is None:
                try:
                    kids = Path(f"/proc/{launcher.pid}/task/{launcher.pid}/children").read_text().split()
                    child = int(kids[0]) if kids else None
                except (OSError, ValueError):
                    pass
            if child is not None:
                anon, file_ = _resident_parts(child)
                anon_mb, file_mb = np.fmax(anon_mb, anon), np.fmax(file_mb, file_)
                tree_mb = np.fmax(tree_mb, _tree_rss_mb(child))
            if kill_when is not None and kill_when():
                wall = time.perf_counter() - deadline + timeout_s
                os.killpg(launcher.pid, 9)
                launcher.wait()
                return Run(
                    wall_s=float(wall),
                    peak_mb=float("nan"),
                    status=-9,
                    anon_mb=float(anon_mb),
                    file_mb=float(file_mb),
                    tree_mb=float(tree_mb),
                )
            if time.perf_counter() > deadline:
                os.killpg(launcher.pid, 9)
                launcher.wait()
                return Run(
                    wall_s=float(timeout_s),
                    peak_mb=float("nan"),
                    status=-9,
                    anon_mb=float(anon_mb),
                    file_mb=float(file_mb),
                    tree_mb=float(tree_mb),
                )
            time.sleep(0.02)
        try:
            result = json.loads(report.read_text())
        except (OSError, ValueError):  # the launcher itself failed
            return Run(wall_s=float("nan"), peak_mb=float("nan"), status=launcher.returncode or -1)
    except BaseException:  # Ctrl-C: the command, in a session of its own, does not get it from the terminal
        if launcher.poll() is None:
            os.killpg(launcher.pid, 9)
            launcher.wait()
        raise
    finally:
        report.unlink(missing_ok=True)
    return Run(
        wall_s=float(result["wall_s"]),
        peak_mb=result["maxrss_kib"] / 1024.0,
        status=os.waitstatus_to_exitcode(result["status"]),
        anon_mb=float(anon_mb),
        file_mb=float(file_mb),
        tree_mb=float(tree_mb),
    )


def sylva_command() -> Optional[str]:
    """Path of the ``sylva`` command (beside this Python first), or None when not installed."""
    here = Path(sys.executable).with_name("sylva")
    if here.exists():
        return str(here)
    return shutil.which("sylva")


def _python_env() -> dict[str, str]:
    env = dict(os.environ)
    return env


def simulate_pair(workdir: Path, label: str, preset: str, step_deg: float, positions: str, seed: int) -> Path:
    """Simulate a pair with the ``forestreg simulate`` command; returns its folder."""
    out = workdir / f"pair_{preset}_{step_deg}_{seed}"
    if not (out / "truth.json").exists():
        subprocess.run(
            [
                sys.executable,
                "-m",
                "forestreg.cli",
                "simulate",
                preset,
                "--out",
                str(out),
                f"--positions={positions}",
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


def _truth(folder: Path) -> tuple[np.ndarray, list[int]]:
    truth = json.loads((folder / "truth.json").read_text())
    ref, mov = (np.array(s["matrix"], dtype=float) for s in truth["scans"][:2])
    return np.linalg.inv(ref) @ mov, [int(s["n_points"]) for s in truth["scans"][:2]]


def _forestreg_matrix(out: Path) -> Optional[np.ndarray]:
    try:
        result = json.loads((out / "result.json").read_text())
    except (OSError, ValueError):
        return None
    return None if result.get("matrix") is None else np.array(result["matrix"], dtype=float)


def _sylva_matrix(out: Path) -> Optional[np.ndarray]:
    try:
        result = json.loads((out / "transforms.json").read_text())
    except (OSError, ValueError):
        return None
    scans = {int(s["index"]): s for s in result.get("scans", [])}
    if not all(i in scans and scans[i].get("registered") for i in (0, 1)):
        return None
    world = {i: np.array(scans[i]["world_from_scan"], dtype=float) for i in (0, 1)}
    return np.linalg.inv(world[0]) @ world[1]


def bench_pair(folder: Path, label: str, runs: int, sylva: Optional[str]) -> dict[str, Any]:
    """Time the commands on one pair, ``runs`` rounds after one untimed warm-up round."""
    a, b = str(folder / "scan_01.laz"), str(folder / "scan_02.laz")
    out_f, out_s = folder / "out_forestreg", folder / "out_sylva"
    reader = "import sys\nfrom forestreg.engine.io import read_scan\nfor p in sys.argv[1:]:\n    read_scan(p)\n"
    commands = {
        "read": [sys.executable, "-c", reader, a, b],
        "forestreg": [sys.executable, "-m", "forestreg.cli", "register", a, b, "--out", str(out_f), "--quiet"],
    }
    if sylva:
        commands["sylva"] = [sylva, "coreg", a, b, "-o", str(out_s), "--quiet"]
    env = _python_env()
    results: dict[str, list[Run]] = {k: [] for k in commands}
    for round_ in range(runs + 1):
        for name, argv in commands.items():
            own = {"forestreg": out_f, "sylva": out_s}.get(name)
            if own is not None and own.exists():
                shutil.rmtree(own)
            run = run_command(argv, env=env)
            if round_:
                results[name].append(run)
    truth, points = _truth(folder)
    row: dict[str, Any] = {"label": label, "points": points, "runs": runs, "raw_mb": sum(points) * 3 * 8 / 1e6}
    for name, rs in results.items():
        row[name] = {
            "wall_s": statistics.median(r.wall_s for r in rs),
            "peak_mb": statistics.median(r.peak_mb for r in rs),
            "anon_mb": statistics.median(r.anon_mb for r in rs),
            "file_mb": statistics.median(r.file_mb for r in rs),
            "status": sorted({r.status for r in rs}),
        }
    for other in [k for k in commands if k != "forestreg"]:
        row[f"forestreg/{other}"] = {
            "wall": statistics.median(f.wall_s / o.wall_s for f, o in zip(results["forestreg"], results[other])),
            "peak": statistics.median(f.peak_mb / o.peak_mb for f, o in zip(results["forestreg"], results[other])),
            "anon": statistics.median(f.anon_mb / o.anon_mb for f, o in zip(results["forestreg"], results[other])),
        }
    if sylva:
        row["sylva/read"] = {
            "wall": statistics.median(s.wall_s / r.wall_s for s, r in zip(results["sylva"], results["read"]))
        }
    for name, matrix in (("forestreg", _forestreg_matrix(out_f)), ("sylva", _sylva_matrix(out_s) if sylva else None)):
        if name in row:
            row[name]["error"] = (
                None if matrix is None else dict(zip(("rotation_deg", "translation_m"), rigid_errors(matrix, truth)))
            )
    return row


def run(*, quick: bool = False, runs: int = 3, workdir: Optional[Path] = None) -> list[dict[str, Any]]:
    """Simulate the pairs and time the commands on each; one row per pair."""
    sylva = sylva_command()
    rows = []
    with tempfile.TemporaryDirectory(prefix="forestreg-peers-") as tmp:
        base = Path(workdir) if workdir is not None else Path(tmp)
        for label, preset, step, positions, seed in QUICK_PAIRS if quick else PAIRS:
            folder = simulate_pair(base, label, preset, step, positions, seed)
            rows.append(bench_pair(folder, label, runs, sylva))
        if not quick:
            label, preset, step, positions, seed = FLOOR_PAIR
            rows.append(
                {
                    **bench_pair(simulate_pair(base, label, preset, step, positions, seed), label, runs, sylva),
                    "floor": True,
                }
            )
    return rows


def _geomean(values: list[float]) -> float:
    return float(np.exp(np.mean(np.log(values)))) if values else float("nan")


def format_rows(rows: list[dict[str, Any]]) -> str:
    """The table: per pair, each command's median wall time and peak memory, and the ratios; the
    floor pair (:data:`FLOOR_PAIR`, when measured) is left out of the means and set against the
    largest pair's Sylva peak instead."""
    floor = next((r for r in rows if r.get("floor")), None)
    rows = [r for r in rows if not r.get("floor")]
    has_sylva = any("sylva" in r for r in rows)
    lines = [
        "Pair registration, whole commands (median of runs; ratios are medians of the run-by-run ratios)",
    ]
    head = (
        f"{'pair':<34} {'':>10} {'read':>9} {'forestreg':>10}"
        + (f" {'Sylva':>9}" if has_sylva else "")
        + f" {'fr/read':>8}"
        + (f" {'fr/Sylva':>9}" if has_sylva else "")
    )
    lines += [head, "-" * len(head)]
    for r in rows:
        syl = r.get("sylva")
        lines.append(
            f"{r['label']:<34} {'wall s':>10} {r['read']['wall_s']:>9.2f} {r['forestreg']['wall_s']:>10.2f}"
            + (f" {syl['wall_s']:>9.2f}" if syl else "")
            + f" {r['forestreg/read']['wall']:>8.2f}"
            + (f" {r['forestreg/sylva']['wall']:>9.2f}" if syl else "")
        )
        lines.append(
            f"{'':<34} {'peak MB':>10} {r['read']['peak_mb']:>9.0f} {r['forestreg']['peak_mb']:>10.0f}"
            + (f" {syl['peak_mb']:>9.0f}" if syl else "")
            + f" {r['forestreg/read']['peak']:>8.2f}"
            + (f" {r['forestreg/sylva']['peak']:>9.2f}" if syl else "")
        )
        lines.append(
            f"{'':<34} {'of it anon.':>10} {r['read']['anon_mb']:>9.0f} {r['forestreg']['anon_mb']:>10.0f}"
            + (f" {syl['anon_mb']:>9.0f}" if syl else "")
            + f" {r['forestreg/read']['anon']:>8.2f}"
            + (f" {r['forestreg/sylva']['anon']:>9.2f}" if syl else "")
            + f"   (file-backed: forestreg {r['forestreg']['file_mb']:.0f}"
            + (f", Sylva {syl['file_mb']:.0f}" if syl else "")
            + ")"
        )
        budget = 3 * r["raw_mb"] + 300
        lines.append(
            f"{'':<34} raw point arrays {r['raw_mb']:.0f} MB: memory budget 3x + 300 = {budget:.0f} MB, "
            f"forestreg {r['forestreg']['peak_mb'] / budget:.2f} of it"
        )
        errors = []
        for name in ("forestreg", "sylva"):
            if name in r:
                e = r[name].get("error")
                errors.append(
                    f"{name} "
                    + (
                        "no result"
                        if e is None
                        else f"{e['rotation_deg']:.4f} deg / {1000 * e['translation_m']:.1f} mm"
                    )
                )
        lines.append(f"{'':<34} error vs truth: " + ", ".join(errors))
    if len(rows) > 1:
        lines.append("-" * len(head))
        g = f"{'geometric mean':<34} {'wall':>10} {'':>9} {'':>10}" + (f" {'':>9}" if has_sylva else "")
        g += f" {_geomean([r['forestreg/read']['wall'] for r in rows]):>8.2f}"
        if has_sylva:
            g += f" {_geomean([r['forestreg/sylva']['wall'] for r in rows if 'forestreg/sylva' in r]):>9.2f}"
        lines.append(g)
        g = f"{'':<34} {'peak':>10} {'':>9} {'':>10}" + (f" {'':>9}" if has_sylva else "")
        g += f" {_geomean([r['forestreg/read']['peak'] for r in rows]):>8.2f}"
        if has_sylva:
            g += f" {_geomean([r['forestreg/sylva']['peak'] for r in rows if 'forestreg/sylva' in r]):>9.2f}"
        lines.append(g)
    if floor is not None:
        lines.append("-" * len(head))
        lines.append(
            f"runtime floor: forestreg register peaks at {floor['forestreg']['peak_mb']:.0f} MB on the {floor['label']} pair "
            f"(Sylva {floor['sylva']['peak_mb']:.0f} MB)"
            if "sylva" in floor
            else f"runtime floor: forestreg register peaks at {floor['forestreg']['peak_mb']:.0f} MB on the {floor['label']} pair"
        )
        largest = max(rows, key=lambda r: r["raw_mb"], default=None)
        if largest is not None and "sylva" in largest:
            half = 0.5 * largest["sylva"]["peak_mb"]
            lines.append(
                f"{'':<15}= {floor['forestreg']['peak_mb'] / largest['sylva']['peak_mb']:.2f}x Sylva's peak on the {largest['label']} pair; "
                f"half of that peak ({half:.0f} MB) leaves {half - floor['forestreg']['peak_mb']:.0f} MB above the floor for "
                f"{largest['raw_mb']:.0f} MB of raw point arrays"
            )
    if not has_sylva:
        lines.append("Sylva not installed (pip install 'forestreg[bench]' or sylva-rs): its columns are left out")
    return "\n".join(lines)


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="forestreg register vs reading the files vs Sylva coreg")
    ap.add_argument("--quick", action="store_true", help="the small pair only")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--workdir", type=Path, help="keep the simulated pairs here (reused when present)")
    args = ap.parse_args()
    print(format_rows(run(quick=args.quick, runs=args.runs, workdir=args.workdir)))
