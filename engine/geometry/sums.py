"""Sums in NumPy's order, compiled: NumPy's pairwise summation of a contiguous float64 array
(``np.add.reduce``) and of a segment (``np.add.reduceat``), so compiled kernels give NumPy's
results to the last bit."""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel

__all__ = ["block_sum", "pairwise_sum", "segment_sum"]


@kernel
def block_sum(a: np.ndarray, start: int, n: int) -> float:
    """NumPy's pairwise sum of ``a[start:start + n]`` for ``n <= 128``: below 8 values one after
    the other, else eight running sums combined in pairs, then the rest."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[start + i]
        return res
    r0, r1, r2, r3 = a[start], a[start + 1], a[start + 2], a[start + 3]
    r4, r5, r6, r7 = a[start + 4], a[start + 5], a[start + 6], a[start + 7]
    i = 8
    whole = n - n % 8
    while i < whole:
        j = start + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[start + i]
        i += 1
    return res


@kernel
def pairwise_sum(a: np.ndarray, start: int, n: int) -> float:
    """Sum of ``a[start:start + n]`` as NumPy's ``add.reduce`` of a contiguous float64 array
    with the initial value 0 takes it: blocks of at most 128 values (:func:`block_sum`), longer
    runs split in two (the first half a multiple of 8) and the halves' sums added. The halving is
    walked with an explicit stack (cached kernels must not recurse)."""
    if n <= 128:
        return block_sum(a, start, n)
    lo = np.empty(64, dtype=np.int64)  # depth <= log2(n)
    size = np.empty(64, dtype=np.int64)
    left = np.empty(64)
    state = np.zeros(64, dtype=np.int64)  # 0: left half pending, 1: right half pending
    top = 0
    lo[0], size[0], state[0] = start, n, 0
    while True:
        if size[top] > 128:  # descend into the left half
            half = size[top] // 2
            half -= half % 8
            lo[top + 1], size[top + 1], state[top + 1] = lo[top], half, 0
            top += 1
            continue
        v = block_sum(a, lo[top], size[top])
        top -= 1
        while top >= 0 and state[top] == 1:  # both halves done: add them, go up
            v = left[top] + v
            top -= 1
        if top < 0:
            return v
        left[top] = v  # left half done: the right half next
        state[top] = 1
        half = size[top] // 2
        half -= half % 8
        lo[top + 1], size[top + 1], state[top + 1] = lo[top] + half, size[top] - half, 0
        top += 1


@kernel
def segment_sum(a: np.ndarray, n: int) -> float:
    """Sum of ``a[:n]`` (n >= 1) as ``np.add.reduceat`` takes a segment: the first value plus the
    pairwise sum of the rest."""
    return a[0] + pairwise_sum(a, 1, n - 1)
