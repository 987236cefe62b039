"""Warm-up: the numerical kernels compiled ahead into the per-version cache, so that no command
pays for it (``forestreg warmup``; ``scripts/setup.sh`` runs it). The front door runs each command
once on small simulated data; this file says where the cache is and whether it is complete."""

from __future__ import annotations


def cache_folder():
    """The per-version kernel cache folder (or None: kernels compiled in memory)."""
    from ..engine.core.jit import kernel_cache_dir

    return kernel_cache_dir()


def cache_is_warm() -> bool:
    """Whether a warm-up completed for this version."""
    from ..engine.core.jit import cache_is_warm as warm

    return warm()


def mark_cache_warm() -> None:
    """Record in the cache folder that the kernels of every module imported so far are compiled,
    with a hash of each source file (what :func:`cache_is_warm` checks)."""
    import json
    import os

    from ..engine.core.atomic import write_text_atomic
    from ..engine.core.jit import WARM_MARK, kernel_cache_dir, warm_record

    folder = kernel_cache_dir()
    if folder:
        os.makedirs(folder, exist_ok=True)
        write_text_atomic(os.path.join(folder, WARM_MARK), json.dumps(warm_record(), indent=1))


def compiled() -> tuple[int, int]:
    """(signatures, kernels) compiled in this process."""
    from ..engine.core.jit import kernels

    done = [k for k in kernels() if k.signatures]
    return sum(len(k.signatures) for k in done), len(done)
