"""What a pair's run imports: neither SciPy's spatial nor its ndimage package (the searches and
filters of ``geometry.nearest`` and ``geometry.filters2d`` stand in for them), nor the whole of
``scipy.linalg`` that numba's BLAS check would import -- and numba's BLAS still works."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT.parent), env.get("PYTHONPATH", "")) if p)
    return env


def _run(code: str, *args, cwd: Path) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, cwd=cwd, env=_env(), timeout=600
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def _pair_files(sim_plot, folder: Path) -> list[Path]:
    """A simulated mixed pair written as two LAZ files in ``folder``."""
    from forestreg.engine.io import write_scan

    plot = sim_plot("mixed_temperate", ((0.0, 0.0), (12.0, -3.0)), seed=2)
    paths = []
    for s in plot.scans:
        paths.append(folder / f"{s.scan.name}.laz")
        write_scan(s.scan, paths[-1])
    return paths


def test_a_small_pair_registers_without_scipys_spatial_and_ndimage_packages(sim_plot, tmp_path):
    """Their import costs a small pair's run about 0.1 s: the pair path uses the searches and
    filters above (SciPy's linear algebra is still imported, by numba)."""
    paths = _pair_files(sim_plot, tmp_path)
    code = (
        "import json, sys\n"
        "from forestreg.app.pair import register_pair\n"
        "o = register_pair(sys.argv[1], sys.argv[2], sys.argv[3])\n"
        "heavy = ('scipy.spatial', 'scipy.ndimage', 'scipy.sparse', 'scipy.linalg')\n"
        "print(json.dumps({'ok': o.result.ok, 'scipy': sorted(m for m in sys.modules if m in heavy or m.startswith(tuple(h + '.' for h in heavy[:3])))}))\n"
    )
    report = _run(code, paths[0], paths[1], tmp_path / "out", cwd=tmp_path)
    assert report == {"ok": True, "scipy": []}


def test_numbas_blas_works_without_the_whole_of_scipy_linalg(tmp_path):
    """The first kernel a process loads leaves ``scipy.linalg`` unimported; a numba function using
    BLAS still compiles and computes, and ``scipy.linalg`` imports whole afterwards."""
    code = (
        "import json, sys\n"
        "import numpy as np, numba\n"
        "from forestreg.engine.geometry.voxel import column_bounds\n"
        "column_bounds(np.arange(9.0).reshape(3, 3))\n"
        "alone = 'scipy.linalg' not in sys.modules and 'scipy.linalg.cython_blas' in sys.modules\n"
        "f = numba.njit(lambda a, b: np.dot(a, b))\n"
        "a = np.arange(16.0).reshape(4, 4)\n"
        "dot = bool(np.array_equal(f(a, a), a @ a))\n"
        "import scipy.linalg\n"
        "from scipy.linalg import cython_blas\n"
        "m = a + 10 * np.eye(4)\n"
        "linalg = bool(np.allclose(scipy.linalg.inv(m) @ m, np.eye(4))) and cython_blas is sys.modules['scipy.linalg.cython_blas']\n"
        "print(json.dumps({'alone': alone, 'dot': dot, 'linalg': linalg}))\n"
    )
    assert _run(code, cwd=tmp_path) == {"alone": True, "dot": True, "linalg": True}


def test_a_small_pairs_command_runs_without_the_cyclic_collector_unless_it_compiles(sim_plot, tmp_path):
    """``forestreg register`` of small scans turns Python's cyclic garbage collector off (its full
    passes over the imports' objects cost a small pair 0.1-0.2 s); a process that has to compile
    kernels turns it on again."""
    paths = _pair_files(sim_plot, tmp_path)
    code = (
        "import gc, json, sys\n"
        "from forestreg import cli\n"
        "from forestreg.engine.core import jit\n"
        "code = cli.main(['register', sys.argv[1], sys.argv[2], '--out', sys.argv[3], '--quiet'], tune_malloc=True)\n"
        "print(json.dumps({'code': code, 'collector': gc.isenabled(), 'compiled': jit._SAID}))\n"
    )
    report = _run(code, paths[0], paths[1], tmp_path / "out", cwd=tmp_path)
    assert report["code"] == 0 and report["collector"] == report["compiled"]
    # a caller's process (no tuning asked) keeps its collector
    code = code.replace(", tune_malloc=True", "")
    report = _run(code, paths[0], paths[1], tmp_path / "out2", cwd=tmp_path)
    assert report["code"] == 0 and report["collector"] is True


def test_compiling_a_kernel_turns_the_cyclic_collector_on(monkeypatch):
    import gc

    from forestreg.engine.core import jit

    monkeypatch.setattr(jit, "_SAID", True)  # nothing said
    gc.disable()
    try:
        jit._say_compiling(jit.__file__)
        assert gc.isenabled()
    finally:
        gc.enable()
