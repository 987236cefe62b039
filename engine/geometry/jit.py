"""Compiled kernels: one decorator for every numba kernel of the geometry and tree code, and a
helper that runs a kernel over blocks of rows on a pool of threads.

Kernels are compiled on first use and cached on disk (beside the source, or in the user's cache
directory when the package folder is read-only; without any writable place they are compiled
in each process). They release the interpreter lock (``nogil``), so blocks of independent rows
run in parallel threads.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numba

__all__ = ["kernel", "run_blocks", "warm_up", "worker_count"]


def kernel(fn: Callable[..., Any] | None = None, **options: Any) -> Any:
    """``numba.njit(cache=True, nogil=True, **options)``; without a writable cache location,
    uncached. Use as ``@kernel`` or ``@kernel(error_model="numpy")``."""
    if fn is None:
        return lambda f: kernel(f, **options)
    try:
        return numba.njit(cache=True, nogil=True, **options)(fn)
    except RuntimeError:  # numba found no directory to cache in
        return numba.njit(nogil=True, **options)(fn)


def warm_up() -> None:
    """Load one small compiled kernel now (from the cache, or compiled): the first kernel a
    process loads starts numba's compiler, LLVM (~0.3 s and ~40 MB, whichever kernel it is; each
    later one takes a few milliseconds). A command calls this in a background thread while its
    files are read (:func:`forestreg.cli.common.import_in_background`), so that the start-up is
    not spent in its first step."""
    import numpy as np

    from .voxel import column_bounds

    column_bounds(np.zeros((1, 3)))  # the signature the commands' own calls load


def worker_count() -> int:
    """Cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def run_blocks(fn: Callable[..., Any], n: int, *args: Any, block: int = 32768, compiles: bool = True) -> None:
    """Call ``fn(start, stop, *args)`` for consecutive blocks of ``block`` rows covering
    ``range(n)``; ``fn`` writes its rows' results into arrays among ``args`` (blocks must be
    independent). The blocks run on the process's pool of one thread per core (:func:`_pool`),
    when there are more than one core; the first block runs alone in the calling thread while
    ``fn`` is a kernel not compiled or loaded yet (one thread compiles it, the others would wait),
    or a Python function (which may call such kernels; ``compiles=False``: it calls none, e.g.
    only NumPy or LAPACK, and all its blocks go to the pool at once). ``fn`` must not wait for
    other blocks (compiled kernels never do): callers in several threads share the pool."""
    if n <= 0:
        return
    starts = list(range(0, n, block))
    if compiles and not getattr(fn, "signatures", None):  # not a kernel, or one not compiled or loaded yet
        fn(0, min(n, block), *args)
        starts = starts[1:]
    if min(worker_count(), len(starts)) <= 1:
        for a in starts:
            fn(a, min(n, a + block), *args)
        return
    pool = _pool()
    for f in [pool.submit(fn, a, min(n, a + block), *args) for a in starts]:
        f.result()


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _pool() -> ThreadPoolExecutor:
    """The threads :func:`run_blocks` runs blocks on: one per core, made on first use and kept
    (a registration calls it hundreds of times; starting threads each time cost ~0.1 s of an ICP
    run). A forked child makes its own."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(worker_count(), thread_name_prefix="forestreg-blocks")
        return _POOL


def _forget_pool() -> None:
    global _POOL, _POOL_LOCK
    _POOL, _POOL_LOCK = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)
