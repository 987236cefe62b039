"""Compiled kernels: one decorator for every numba kernel of the geometry and tree code, and a
helper that runs a kernel over blocks of rows on a pool of threads.

Kernels are compiled on first use and cached on disk (beside the source, or in the user's cache
directory when the package folder is read-only; without any writable place they are compiled
in each process). They release the interpreter lock (``nogil``), so blocks of independent rows
run in parallel threads.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numba

__all__ = ["kernel", "run_blocks", "worker_count"]


def kernel(fn: Callable[..., Any] | None = None, **options: Any) -> Any:
    """``numba.njit(cache=True, nogil=True, **options)``; without a writable cache location,
    uncached. Use as ``@kernel`` or ``@kernel(error_model="numpy")``."""
    if fn is None:
        return lambda f: kernel(f, **options)
    try:
        return numba.njit(cache=True, nogil=True, **options)(fn)
    except RuntimeError:  # numba found no directory to cache in
        return numba.njit(nogil=True, **options)(fn)


def worker_count() -> int:
    """Cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def run_blocks(fn: Callable[..., Any], n: int, *args: Any, block: int = 32768) -> None:
    """Call ``fn(start, stop, *args)`` for consecutive blocks of ``block`` rows covering
    ``range(n)``; ``fn`` writes its rows' results into arrays among ``args`` (blocks must be
    independent). The first block runs in the calling thread (where the kernel is compiled or
    loaded, never in two threads at once), the others on a pool of threads when there are more
    than one core."""
    if n <= 0:
        return
    fn(0, min(n, block), *args)
    starts = list(range(block, n, block))
    workers = min(worker_count(), len(starts))
    if workers <= 1:
        for a in starts:
            fn(a, min(n, a + block), *args)
        return
    with ThreadPoolExecutor(workers) as pool:
        for f in [pool.submit(fn, a, min(n, a + block), *args) for a in starts]:
            f.result()
