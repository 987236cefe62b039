"""Warm-up: the numerical kernels compiled ahead into the per-version cache, so that no command
pays for it (``forestreg warmup``; ``scripts/setup.sh`` runs it). The front door runs each command
once on small simulated data; this file says where the cache is and whether it is complete."""

from __future__ import annotations


def cache_folder():
    """The per-version kernel cache folder (or None: kernels compiled in memory)."""
    from ..engine.geometry.jit import kernel_cache_dir

    return kernel_cache_dir()


def cache_is_warm() -> bool:
    """Whether a warm-up completed for this version."""
    from ..engine.geometry.jit import cache_is_warm as warm

    return warm()


def mark_cache_warm() -> None:
    """Record that the cache is complete."""
    from ..engine.geometry.jit import mark_cache_warm as mark

    mark()


def compiled() -> tuple[int, int]:
    """(signatures, kernels) compiled in this process."""
    from ..engine.geometry.jit import kernels

    done = [k for k in kernels() if k.signatures]
    return sum(len(k.signatures) for k in done), len(done)
