"""Same input, same answer: the compiled-kernel cache when several processes compile at once."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import forestreg

#: The folder that holds the ``forestreg`` package (for the child processes' import path).
PACKAGE_PARENT = str(Path(forestreg.__file__).resolve().parent.parent)


def _env(cache: Path, **extra: str) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([PACKAGE_PARENT] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env["NUMBA_CACHE_DIR"] = str(cache)
    env.pop("OPENBLAS_NUM_THREADS", None)
    env.pop("OMP_NUM_THREADS", None)
    env.update(extra)
    return env


# ----------------------------------------------------------------------------------- kernel cache

_KERNEL_MODULE = '''
from forestreg.engine.geometry.jit import kernel

@kernel
def weighted_sum(a):
    s = a[0] * 0
    for i in range(a.shape[0]):
        s += a[i] * (i % 3)
    return s
'''

_KERNEL_RUN = '''
import sys, time
import numpy as np
sys.path.insert(0, sys.argv[3])
import kmod
a = np.arange(50, dtype=sys.argv[1])
start = float(sys.argv[2])
while time.time() < start:
    time.sleep(0.0005)
print(float(kmod.weighted_sum(a)))
'''


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
        procs = [subprocess.Popen([sys.executable, str(tmp_path / "run.py"), dtype, str(start), str(tmp_path)],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(cache), text=True)
                 for dtype in ("float64", "float32", "int64", "int32")]
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
    swapped = {key: (by_dtype["float32"] if str(key[0][0].dtype) == "float64" else name) for key, name in overloads.items()}
    with index[0].open("rb") as f:
        version = pickle.load(f)
        stamp, _ = pickle.loads(f.read())
    with index[0].open("wb") as f:
        pickle.dump(version, f, protocol=-1)
        f.write(pickle.dumps((stamp, swapped), protocol=-1))
    run = subprocess.run([sys.executable, str(tmp_path / "run.py"), "float64", "0", str(tmp_path)], capture_output=True, text=True,
                         env=_env(cache), timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert float(run.stdout.strip()) == expected
