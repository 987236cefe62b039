"""Benchmark: a plot of ten ~30 M-point scans (0.04 deg RIEGL-sized) registered with
``forestreg plot`` and merged out of core into one COPC file, against a 4 GB memory limit.

The plot is simulated at 0.1 deg (``forestreg simulate mixed_temperate``, an 80 m plot, about
3.1 M points a scan): a centre scan at (0, 0) and the others evenly on a ring 12 m around it
(:func:`plot_positions`), as a surveyor places them. Each scan is then densified to ~30 M points
(:func:`benchmarks.big_scan.densify`: ten copies with millimetre jitter, in the scan's own file
coordinates, so the simulator's truth still holds). Then, one child process a stage (wall time
from the parent's clock, peak resident memory from the operating system: ``os.wait4``
``ru_maxrss``, :func:`benchmarks.peers.run_command`):

1. ``forestreg plot S01 ... S10 --out DIR`` (each scan linked to the centre scan, the report);
2. ``sylva coreg S01 ... S10 -o DIR`` on the same files, its poses checked against the same truth;
3. ``forestreg plot ... --merged DIR.copc.laz`` killed with SIGKILL once half its links are
   registered, then the same command again: it must resume (keep the links done) and write the
   merged COPC file;
4. ``forestreg project run DIR/project.json --merged DIR.laz``: the merged cloud as LAZ from the
   finished project.

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
    ring = [
        (ring_m * math.cos(2 * math.pi * k / (n_scans - 1)), ring_m * math.sin(2 * math.pi * k / (n_scans - 1)))
        for k in range(n_scans - 1)
    ]
    return [(0.0, 0.0)] + [(round(x, 2), round(y, 2)) for x, y in ring]


def simulate(workdir: Path, n_scans: int) -> Path:
    """The simulated plot (``scan_XX.laz`` + ``truth.json``) under ``workdir``; simulated only
    when missing."""
    out = workdir / f"plot{n_scans}_{PRESET}_{STEP_DEG}_{SEED}"
    if not (out / "truth.json").exists():
        positions = ";".join(f"{x:g},{y:g}" for x, y in plot_positions(n_scans))
        subprocess.run(
            [
                sys.executable,
                "-m",
                "forestreg.cli",
                "simulate",
                PRESET,
                "--out",
                str(out),
                f"--positions={positions}",
                "--step",
                str(STEP_DEG),
                "--size",
                str(SIZE_M),
                "--seed",
                str(SEED),
                "--quiet",
            ],
            check=True,
            stdout=subprocess.DEVNULL,
            env=peers._python_env(),
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
    return {
        Path(k).stem: (None if v.get("matrix") is None else np.array(v["matrix"], dtype=float))
        for k, v in scans.items()
    }


def _point_count(path: Path) -> Optional[int]:
    """The point count in a LAS/LAZ/COPC header (laspy), None when the file is missing or unreadable."""
    import laspy

    try:
        with laspy.open(str(path)) as f:
            return int(f.header.point_count)
    except (OSError, ValueError, laspy.errors.LaspyException):
        return None


def _links_done(out: Path) -> int:
    """Links registered so far in the project file a ``plot`` run keeps saving into ``out``."""
    try:
        links = json.loads((out / "project.json").read_text()).get("links", [])
    except (OSError, ValueError, AttributeError):
        return 0
    return sum(1 for link in links if isinstance(link, dict) and (link.get("result") or {}).get("status") == "ok")


def _sylva_poses(out: Path, files: list[Path]) -> dict[str, Optional[np.ndarray]]:
    """Sylva's poses (``transforms.json``, scans by their index on its command line) relative to
    the first scan, by scan file stem; {} when it wrote none."""
    try:
        scans = json.loads((out / "transforms.json").read_text()).get("scans", [])
        world = {int(s["index"]): np.array(s["world_from_scan"], dtype=float) for s in scans if s.get("registered")}
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    if 0 not in world:
        return {}
    return {files[i].stem: np.linalg.inv(world[0]) @ m for i, m in world.items() if i < len(files)}


def _errors(
    files: list[Path], poses: dict[str, Optional[np.ndarray]], truth: dict[str, np.ndarray]
) -> dict[str, Optional[dict[str, float]]]:
    """Each non-centre scan's pose error against the truth (None: not registered)."""
    errors: dict[str, Optional[dict[str, float]]] = {}
    for path in files[1:]:
        pose = poses.get(path.stem)
        errors[path.stem] = (
            None if pose is None else dict(zip(("rotation_deg", "translation_m"), rigid_errors(pose, truth[path.stem])))
        )
    return errors


def _stage(result: "peers.Run", **extra: Any) -> dict[str, Any]:
    return {"wall_s": result.wall_s, "peak_mb": result.peak_mb, "status": result.status, **extra}


def run(
    scans: int = 10,
    copies: int = 10,
    workdir: Optional[Path] = None,
    *,
    timeout_s: float = 4 * 3600.0,
    with_sylva: bool = True,
) -> dict[str, Any]:
    """Simulate and densify the plot (or reuse it), then, one child process a stage:

    1. ``register``: ``forestreg plot`` (the links only), against
    2. ``sylva``: ``sylva coreg S01 ... S10`` on the same files (when Sylva is installed);
    3. ``stopped``: ``forestreg plot --merged OUT.copc.laz`` killed with SIGKILL once half its
       links are registered, and ``resumed``: the same command run again;
    4. ``laz``: ``forestreg project run`` of the finished project with ``--merged OUT.laz``.

    Returns the row: points, budgets, each stage's wall s / peak MB / exit status, the pose errors
    against the truth, the merged files' point counts."""
    if scans < 2:
        raise ValueError("a plot needs at least two scans")
    base = Path(workdir) if workdir is not None else Path("bench_out")
    base.mkdir(parents=True, exist_ok=True)
    plot = simulate(base, scans)
    files = densified(plot, copies)
    points = [_point_count(p) or 0 for p in files]
    truth = _truth(plot)
    env = peers._python_env()
    forestreg = [sys.executable, "-m", "forestreg.cli"]
    stages: dict[str, dict[str, Any]] = {}
    # the kernels compiled and cached before anything is timed (a no-op when they are)
    subprocess.run(
        [*forestreg, "warmup", "--quiet"], check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env
    )

    out_reg = plot / f"register_x{copies}"
    shutil.rmtree(out_reg, ignore_errors=True)
    result = peers.run_command(
        [*forestreg, "plot", *map(str, files), "--out", str(out_reg), "--quiet"],
        env=env,
        timeout_s=timeout_s,
        log=plot / f"register_x{copies}.log",
    )
    stages["register"] = _stage(result, errors=_errors(files, _poses(out_reg), truth))
    sylva = peers.sylva_command() if with_sylva else None
    if sylva:
        out_sylva = plot / f"sylva_x{copies}"
        shutil.rmtree(out_sylva, ignore_errors=True)
        result = peers.run_command(
            [sylva, "coreg", *map(str, files), "-o", str(out_sylva), "--quiet"],
            env=env,
            timeout_s=timeout_s,
            log=plot / f"sylva_x{copies}.log",
        )
        stages["sylva"] = _stage(result, errors=_errors(files, _sylva_poses(out_sylva, files), truth))

    out, merged = plot / f"out_x{copies}", plot / f"merged_x{copies}.copc.laz"
    shutil.rmtree(out, ignore_errors=True)
    merged.unlink(missing_ok=True)
    argv = [*forestreg, "plot", *map(str, files), "--out", str(out), "--merged", str(merged), "--quiet"]
    half = max(1, (scans - 1) // 2)
    result = peers.run_command(
        argv,
        env=env,
        timeout_s=timeout_s,
        log=plot / f"stopped_x{copies}.log",
        kill_when=lambda: _links_done(out) >= half,
    )
    stages["stopped"] = _stage(result, links_done=_links_done(out), merged_left=merged.exists())
    log = plot / f"resumed_x{copies}.log"
    result = peers.run_command(argv, env=env, timeout_s=timeout_s, log=log)
    said = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.startswith("resuming")]
    stages["resumed"] = _stage(
        result,
        errors=_errors(files, _poses(out), truth),
        merged_points=_point_count(merged),
        note=said[0] if said else "",
    )
    laz = plot / f"merged_x{copies}.laz"
    laz.unlink(missing_ok=True)
    result = peers.run_command(
        [*forestreg, "project", "run", str(out / "project.json"), "--out", str(out), "--merged", str(laz), "--quiet"],
        env=env,
        timeout_s=timeout_s,
        log=plot / f"laz_x{copies}.log",
    )
    stages["laz"] = _stage(result, errors=_errors(files, _poses(out), truth), merged_points=_point_count(laz))
    raw_mb = max(points) * 3 * 8 / 1e6
    return {
        "scans": scans,
        "copies": copies,
        "points": points,
        "total_points": sum(points),
        "raw_mb_largest": raw_mb,
        "budget_mb": 3 * raw_mb + 300,
        "limit_mb": LIMIT_MB,
        "stages": stages,
        "registered_points": sum(n for p, n in zip(files, points) if _poses(out).get(p.stem) is not None),
    }


def _worst(errors: Optional[dict[str, Optional[dict[str, float]]]]) -> str:
    if not errors:
        return f"{'-':>10} {'-':>9}"
    if any(e is None for e in errors.values()):
        missing = sum(e is None for e in errors.values())
        return f"{f'{missing} unregistered':>20}"
    return f"{max(e['rotation_deg'] for e in errors.values()):>10.4f} {1000 * max(e['translation_m'] for e in errors.values()):>9.1f}"


STAGE_NAMES = {
    "register": "forestreg plot (links)",
    "sylva": "Sylva coreg (same scans)",
    "stopped": "plot --merged .copc.laz, kill -9",
    "resumed": "the same command again",
    "laz": "project run --merged .laz",
}


def format_row(row: dict[str, Any]) -> str:
    """The table of one run: each stage's wall time and peak against the 4 GB limit, the pose
    errors, the merged files' counts, and forestreg's ratios to Sylva."""
    st = row["stages"]
    lines = [
        f"Big plot: {row['scans']} scans x ~{np.mean(row['points']) / 1e6:.1f} M points = {row['total_points'] / 1e6:.1f} M "
        f"(0.1 deg scans densified x{row['copies']})",
        f"{'stage':<34} {'wall s':>8} {'peak MB':>8} {'/4 GB':>6} {'worst deg':>10} {'worst mm':>9} {'merged pts':>12} {'exit':>5}",
        "-" * 98,
    ]
    for key, name in STAGE_NAMES.items():
        if key not in st:
            continue
        s = st[key]
        peak = s["peak_mb"]
        merged = s.get("merged_points")
        lines.append(
            f"{name:<34} {s['wall_s']:>8.0f} {peak:>8.0f} {peak / row['limit_mb']:>6.2f} {_worst(s.get('errors'))} "
            f"{merged if merged is not None else '-':>12} {s['status']:>5}"
        )
    if "sylva" in st and st["sylva"]["status"] == 0 and st["register"]["status"] == 0:
        lines.append(
            f"forestreg / Sylva: wall {st['register']['wall_s'] / st['sylva']['wall_s']:.2f}x, "
            f"peak {st['register']['peak_mb'] / st['sylva']['peak_mb']:.2f}x"
        )
    stopped = st["stopped"]
    lines.append(
        f"stopped by SIGKILL after {stopped['links_done']} of {row['scans'] - 1} links ({stopped['wall_s']:.0f} s in)"
        + ("; a merged file was left behind" if stopped["merged_left"] else "; no merged file left behind")
        + (f'; the rerun said: "{st["resumed"]["note"]}"' if st["resumed"]["note"] else "; the rerun did NOT resume")
    )
    for key in ("resumed", "laz"):
        n = st[key].get("merged_points")
        if n is not None and n != row["registered_points"]:
            lines.append(
                f"MISMATCH: {STAGE_NAMES[key]} merged {n} points, the registered scans hold {row['registered_points']}"
            )
    lines.append(
        f"memory budget: 3x the raw arrays of the largest scan ({row['raw_mb_largest']:.0f} MB) + 300 = {row['budget_mb']:.0f} MB; "
        f"limit {row['limit_mb']:.0f} MB"
    )
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(
        description="forestreg plot with a merged COPC output on ten ~30 M-point scans: wall, peak memory, accuracy"
    )
    ap.add_argument(
        "--scans",
        type=int,
        default=10,
        help="scans in the plot: a centre scan and the rest on a 12 m ring (default 10)",
    )
    ap.add_argument(
        "--copies",
        type=int,
        default=10,
        help="copies of each 0.1 deg scan (~3.1 M points) in its dense scan (default 10: ~31 M)",
    )
    ap.add_argument(
        "--workdir",
        type=Path,
        help="keep the simulated and densified scans here (default bench_out/; reused when present)",
    )
    ap.add_argument("--json", type=Path, help="also write the row to this JSON file")
    ap.add_argument("--no-sylva", action="store_true", help="leave out Sylva's run")
    args = ap.parse_args()
    row = run(args.scans, args.copies, args.workdir, with_sylva=not args.no_sylva)
    peers.show_rows(format_row(row), row, args.json)
