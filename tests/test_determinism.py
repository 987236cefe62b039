"""Same input, same answer: every command gives byte-identical outputs (timings aside) however it
is run.

Each command of the stress test runs 5 times on small real and simulated clouds: 3 runs at the
same time on a kernel cache that starts empty (they compile the kernels while a busy process
loads the machine), 1 run on a single core (one thread for the kernels' blocks, for OpenMP and for
BLAS) and 1 run alone with two BLAS and OpenMP threads. The outputs of all five are compared file
by file, with the timing fields removed. The kernel cache is also checked directly: processes
compiling different signatures of one kernel at the same moment leave entries that each hold the
signature their index names.
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import forestreg

#: The folder that holds the ``forestreg`` package (for the child processes' import path).
PACKAGE_PARENT = str(Path(forestreg.__file__).resolve().parent.parent)

#: Keys of JSON outputs whose values are durations or clock times.
#: Also the batch's record of how a plot ran, not what it gave: the run's id, the Dask worker's
#: address, the process id and the peak memory.
TIMING_KEYS = re.compile(
    r"^(timings|seconds|elapsed|started|finished|created|updated|date|time|.*_s|.*_seconds|.*_time"
    r"|run|worker|pid|peak_mb)$"
)
#: CSV columns (and HTML table heads) holding durations, and the batch's worker and peak memory.
TIMING_COLUMNS = re.compile(r"^(seconds|elapsed|.*_s|time|time \(s\)|duration.*|worker|peak_mb|peak MB)$", re.I)
#: Durations and clock times written in text (reports, logs): "12.3 s", "0.8 s", "1 min 3 s",
#: "generated 2026-11-28 09:33", "seconds: 119.2", a timings block ``"icp_s": 1.93``.
TIMING_TEXT = re.compile(
    rb"\d{4}-\d\d-\d\d[ T]\d\d:\d\d(:\d\d(\.\d+)?)?|\d+(\.\d+)?\s?(s|ms|min)\b|seconds:?\s*\d+(\.\d+)?"
    rb"|(&quot;|\")\w+_s(&quot;|\"):\s*[-+.\de]+"
)


def _env(cache: Path, **extra: str) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [PACKAGE_PARENT] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    )
    env["NUMBA_CACHE_DIR"] = str(cache)
    env.pop("OPENBLAS_NUM_THREADS", None)
    env.pop("OMP_NUM_THREADS", None)
    env.update(extra)
    return env


def _start(argv: list[str], out: Path, cache: Path, *, one_core: bool = False, **extra: str) -> subprocess.Popen:
    """A ``forestreg`` process writing into ``out`` (its stdout and stderr into ``out``.log)."""
    preexec = None
    if one_core:
        cpu = min(os.sched_getaffinity(0))
        extra = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1", **extra}

        def preexec() -> None:
            os.sched_setaffinity(0, {cpu})

    log = open(f"{out}.log", "wb")
    argv = [a.replace("{OUT}", str(out)) for a in argv]
    return subprocess.Popen(
        [sys.executable, "-m", "forestreg.cli", *argv, "-q"],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=_env(cache, **extra),
        preexec_fn=preexec,
    )


def _wait(proc: subprocess.Popen, out: Path, timeout: float = 600) -> None:
    code = proc.wait(timeout=timeout)
    assert code in (0, 1), f"{out.name}: exit {code}\n" + Path(f"{out}.log").read_text(errors="replace")[-3000:]


def _burner() -> subprocess.Popen:
    """A process that keeps one core busy (the machine loaded)."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def _strip_json(value):
    if isinstance(value, dict):
        return {k: _strip_json(v) for k, v in value.items() if not TIMING_KEYS.match(str(k))}
    if isinstance(value, list):
        return [_strip_json(v) for v in value]
    return value


def _without_timing_columns(html: bytes) -> bytes:
    """An HTML page's tables without their columns of durations (headed ``seconds`` & co.)."""
    parts = re.split(rb"(<table.*?</table>)", html, flags=re.S)
    for k, table in enumerate(parts):
        if not table.startswith(b"<table"):
            continue
        heads = [
            re.sub(rb"<[^>]+>", b"", h).strip().decode(errors="replace")
            for h in re.findall(rb"<th[^>]*>(.*?)</th>", table, flags=re.S)
        ]
        drop = {i for i, h in enumerate(heads) if TIMING_COLUMNS.match(h)}
        if drop:

            def row(m: re.Match) -> bytes:
                cells = re.findall(rb"<td[^>]*>.*?</td>", m.group(0), flags=re.S)
                return b"<tr>" + b"".join(c for i, c in enumerate(cells) if i not in drop) + b"</tr>"

            parts[k] = re.sub(rb"<tr[^>]*>.*?</tr>", row, table, flags=re.S)
    return b"".join(parts)


def _normalised(path: Path, root: Path) -> bytes:
    """A file's bytes with its timing fields removed, and the run's own output folder named alike
    (the folders of the runs have one name, in different parents: a project is named after it)."""
    data = path.read_bytes().replace(str(root).encode(), b"{OUT}")
    if path.suffix == ".json":
        return json.dumps(_strip_json(json.loads(data)), sort_keys=True, indent=1).encode()
    if path.suffix == ".csv":
        rows = list(csv.reader(io.StringIO(data.decode())))
        if rows:
            drop = {k for k, name in enumerate(rows[0]) if TIMING_COLUMNS.match(name)}
            rows = [[v for k, v in enumerate(r) if k not in drop] for r in rows]
        return "\n".join(",".join(r) for r in rows).encode()
    if path.suffix in (".html", ".txt", ".log", ".md"):
        return TIMING_TEXT.sub(b"{T}", _without_timing_columns(data) if path.suffix == ".html" else data)
    return data


def _outputs(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): _normalised(p, out) for p in sorted(out.rglob("*")) if p.is_file()}


def _differences(a: dict[str, bytes], b: dict[str, bytes]) -> list[str]:
    lines = []
    for name in sorted(set(a) | set(b)):
        if a.get(name) != b.get(name):
            if name not in a or name not in b:
                lines.append(f"{name}: only in {'the first' if name in a else 'the other'} run")
                continue
            x, y = a[name], b[name]
            k = next((i for i in range(min(len(x), len(y))) if x[i] != y[i]), min(len(x), len(y)))
            lines.append(
                f"{name}: {len(x)} vs {len(y)} bytes, first difference at byte {k}: "
                f"{x[max(0, k - 60) : k + 60]!r} vs {y[max(0, k - 60) : k + 60]!r}"
            )
    return lines


# ----------------------------------------------------------------------------------------- inputs


def _crop(scan, keep: np.ndarray, path: Path) -> Path:
    from forestreg.engine.core.scan import Scan
    from forestreg.engine.io import write_scan

    write_scan(Scan.from_points(scan.points[keep], origin_shift=scan.origin_shift), path)
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, shared_data) -> dict[str, Path]:
    """Small inputs: a simulated 3-scan plot (register, plot), a crop of the real TLS plot
    ``pine_plot.laz`` and of the real ALS stand ``lidR_MixedConifer.laz`` (trees), the real MLS clip
    thinned and turned 30 deg onto the real ALS clip (coregister), and two plots of ALS crops
    (batch)."""
    from forestreg.engine.core.scan import Scan
    from forestreg.engine.core.transform import matrix_from_yaw
    from forestreg.engine.io import read_scan, write_scan
    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import simulate_plot

    root = tmp_path_factory.mktemp("determinism_inputs")
    write_simulated_plot(
        simulate_plot("planted_conifer", [(0, 0), (8, 0), (4, 7)], seed=3, angular_step_deg=0.5, size_m=26),
        root / "plot",
    )
    tls = read_scan(shared_data / "pine_plot.laz")
    c = np.median(tls.points[:, :2], axis=0)
    _crop(tls, np.all(np.abs(tls.points[:, :2] - c) <= 3.5, axis=1), root / "tls.laz")
    als = read_scan(shared_data / "lidR_MixedConifer.laz")
    lo = als.points[:, :2].min(axis=0)
    _crop(als, np.all((als.points[:, :2] >= lo + 10) & (als.points[:, :2] <= lo + 50), axis=1), root / "als.laz")
    (root / "plots" / "p1").mkdir(parents=True)
    (root / "plots" / "p2").mkdir(parents=True)
    _crop(
        als,
        np.all((als.points[:, :2] >= lo + 50) & (als.points[:, :2] <= lo + 80), axis=1),
        root / "plots" / "p1" / "cloud.laz",
    )
    _crop(
        als,
        np.all((als.points[:, :2] >= lo + [0, 50]) & (als.points[:, :2] <= lo + [30, 80]), axis=1),
        root / "plots" / "p2" / "cloud.laz",
    )
    mls = read_scan(shared_data / "spanner_MLS_Clip.laz")
    a = matrix_from_yaw(30.0, np.array([5.0, -3.0, 1.0]))
    p = mls.points[::3]
    write_scan(Scan.from_points(p @ a[:3, :3].T + a[:3, 3], origin_shift=np.zeros(3)), root / "ground.laz")
    return {
        "s1": root / "plot" / "scan_01.laz",
        "s2": root / "plot" / "scan_02.laz",
        "s3": root / "plot" / "scan_03.laz",
        "tls": root / "tls.laz",
        "als": root / "als.laz",
        "plots": root / "plots",
        "ground": root / "ground.laz",
        "uav": shared_data / "spanner_ALS_Clip.laz",
    }


#: name -> the command line ({OUT}: the output folder; other braces: :func:`inputs`).
COMMANDS = {
    "register": ["register", "{s1}", "{s2}", "--out", "{OUT}"],
    "plot": ["plot", "{s1}", "{s2}", "{s3}", "--out", "{OUT}", "--pairs", "all"],  # every pair: links on two threads
    "coregister": ["coregister", "{ground}", "{uav}", "--out", "{OUT}"],
    "trees_als": ["trees", "{als}", "--out", "{OUT}"],
    "trees_tls": ["trees", "{tls}", "--out", "{OUT}", "--no-report"],
    "batch": ["batch", "{plots}", "--out", "{OUT}", "--workers", "2", "--command", "trees", "--extra=--no-report"],
}


@pytest.mark.slow
def test_every_command_gives_the_same_bytes_five_times(inputs, tmp_path):
    """Per command: runs 1-3 at once (the kernel cache empty before the first command, a busy
    process beside them), run 4 on one core with one thread everywhere, run 5 alone with two BLAS
    and OpenMP threads; every output file of the five the same, timings aside."""
    cache = tmp_path / "kernel_cache"  # empty: the first runs compile the kernels at the same time
    failures = []
    t0 = time.perf_counter()
    burned = 0.0  # CPU seconds of the busy process
    for name, template in COMMANDS.items():
        argv = [a.format(**{k: str(v) for k, v in inputs.items()}, OUT="{OUT}") for a in template]
        outs = [tmp_path / f"run{k}" / name for k in range(1, 6)]
        for out in outs:
            out.parent.mkdir(exist_ok=True)
        burner = _burner()
        try:
            procs = [_start(argv, out, cache) for out in outs[:3]]
            for proc, out in zip(procs, outs):
                _wait(proc, out)
        finally:
            burner.kill()
            _, _, usage = os.wait4(burner.pid, 0)
            burned += usage.ru_utime + usage.ru_stime
        _wait(_start(argv, outs[3], cache, one_core=True), outs[3])
        _wait(_start(argv, outs[4], cache, OPENBLAS_NUM_THREADS="2", OMP_NUM_THREADS="2"), outs[4])
        first = _outputs(outs[0])
        assert first, f"{name}: no output\n" + Path(f"{outs[0]}.log").read_text(errors="replace")[-2000:]
        for k, out in enumerate(outs[1:], start=2):
            diff = _differences(first, _outputs(out))
            if diff:
                failures.append(f"{name}, run {k} against run 1:\n  " + "\n  ".join(diff[:5]))
        children = resource.getrusage(resource.RUSAGE_CHILDREN)
        print(
            f"{name}: 5 runs, {len(first)} files; so far {time.perf_counter() - t0:.0f} s, "
            f"{children.ru_utime + children.ru_stime - burned:.0f} s of CPU in the runs"
        )
    assert not failures, "\n".join(failures)


# ----------------------------------------------------------------------------------- kernel cache

_KERNEL_MODULE = """
from forestreg.engine.core.jit import kernel

@kernel
def weighted_sum(a):
    s = a[0] * 0
    for i in range(a.shape[0]):
        s += a[i] * (i % 3)
    return s
"""

_KERNEL_RUN = """
import sys, time
import numpy as np
sys.path.insert(0, sys.argv[3])
import kmod
a = np.arange(50, dtype=sys.argv[1])
start = float(sys.argv[2])
while time.time() < start:
    time.sleep(0.0005)
print(float(kmod.weighted_sum(a)))
"""


def test_kernel_cache_with_processes_compiling_at_once(tmp_path, monkeypatch):
    """Four processes compile four signatures of one kernel into an empty cache at the same
    moment, twice over (the second time they load); every result is right and every entry of the
    cache holds the signature its index names. Then the index is made to name the float32 code
    for the float64 signature (what two processes choosing one data file for two signatures
    leave behind): the float64 call is compiled again, not run on the wrong code."""
    import pickle

    (tmp_path / "kmod.py").write_text(_KERNEL_MODULE)
    (tmp_path / "run.py").write_text(_KERNEL_RUN)
    cache = tmp_path / "cache"
    expected = float(sum(i * (i % 3) for i in range(50)))
    for round_ in range(2):
        start = time.time() + 6.0  # all four imported by then
        procs = [
            subprocess.Popen(
                [sys.executable, str(tmp_path / "run.py"), dtype, str(start), str(tmp_path)],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                env=_env(cache),
                text=True,
            )
            for dtype in ("float64", "float32", "int64", "int32")
        ]
        for proc in procs:
            out, err = proc.communicate(timeout=300)
            assert proc.returncode == 0, err[-2000:]
            assert float(out.strip()) == expected
    index = list(cache.rglob("kmod.weighted_sum-*.nbi"))
    assert len(index) == 1
    with index[0].open("rb") as f:
        pickle.load(f)  # numba's version
        _, overloads = pickle.loads(f.read())
    assert len(overloads) == 4  # none lost
    monkeypatch.syspath_prepend(str(tmp_path))  # the entries name the kernel's module
    for key, data_name in overloads.items():
        payload = pickle.loads((index[0].parent / data_name).read_bytes())
        assert tuple(payload[3].args) == tuple(key[0])

    by_dtype = {str(key[0][0].dtype): name for key, name in overloads.items()}
    swapped = {
        key: (by_dtype["float32"] if str(key[0][0].dtype) == "float64" else name) for key, name in overloads.items()
    }
    with index[0].open("rb") as f:
        version = pickle.load(f)
        stamp, _ = pickle.loads(f.read())
    with index[0].open("wb") as f:
        pickle.dump(version, f, protocol=-1)
        f.write(pickle.dumps((stamp, swapped), protocol=-1))
    run = subprocess.run(
        [sys.executable, str(tmp_path / "run.py"), "float64", "0", str(tmp_path)],
        capture_output=True,
        text=True,
        env=_env(cache),
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert float(run.stdout.strip()) == expected


def test_link_information_matrix_is_open3d_s_summed_in_a_fixed_order():
    """The global adjustment's information matrix of a link: the same as open3d's (which adds
    its threads' sums as they finish, so its last bits change from call to call), the same bytes
    every call."""
    import open3d as o3d

    from forestreg.engine.core.transform import matrix_from_yaw
    from forestreg.engine.tls.plot import information_matrix

    rng = np.random.default_rng(0)
    reference = rng.random((40000, 3)) * 20.0
    moving = reference + rng.normal(0.0, 0.01, reference.shape)
    matrix = matrix_from_yaw(0.3, np.array([0.01, 0.02, 0.0]))
    ours = [information_matrix(moving, reference, 0.1, matrix) for _ in range(4)]
    assert all(m.tobytes() == ours[0].tobytes() for m in ours)
    cloud = o3d.geometry.PointCloud
    theirs = np.asarray(
        o3d.pipelines.registration.get_information_matrix_from_point_clouds(
            cloud(o3d.utility.Vector3dVector(moving)), cloud(o3d.utility.Vector3dVector(reference)), 0.1, matrix
        )
    )
    assert np.abs(ours[0] - theirs).max() <= 1e-12 * np.abs(theirs).max()


def test_warmup_records_the_kernel_sources_and_is_skipped_while_they_are_unchanged(tmp_path, monkeypatch, capsys):
    """``forestreg warmup`` leaves a record of the kernels' source files and their hashes; a
    second warm-up with those files unchanged compiles nothing, and a changed file makes the
    cache cold again (the first command then says it compiles)."""
    import hashlib
    import json

    import numba

    from forestreg.cli import main
    from forestreg.engine.core import jit
    from forestreg.engine.geometry import voxel

    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path))
    assert jit.kernel_cache_dir() == str(tmp_path) and not jit.cache_is_warm()
    source = Path(voxel.__file__)
    (tmp_path / jit.WARM_MARK).write_text(
        json.dumps({"files": {str(source): hashlib.sha256(source.read_bytes()).hexdigest()}})
    )
    # a kernel file the record does not hold (a module added since) makes the cache cold
    assert (
        not jit.cache_is_warm()
        and jit.cache_is_warm([str(source)])
        and not jit.cache_is_warm([str(source.with_name("icp.py"))])
    )
    every = jit.kernel_source_files()
    assert str(source) in every and len(every) >= 15
    (tmp_path / jit.WARM_MARK).write_text(
        json.dumps({"files": {f: hashlib.sha256(Path(f).read_bytes()).hexdigest() for f in every}})
    )
    assert jit.cache_is_warm()
    assert main(["warmup"]) == 0
    assert "compiled already" in capsys.readouterr().out
    (tmp_path / jit.WARM_MARK).write_text(json.dumps({"files": {str(source): "0" * 64}}))
    assert not jit.cache_is_warm()
