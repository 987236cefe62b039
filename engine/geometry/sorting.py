"""Stable sorting of non-negative integer keys (voxel and grid-cell keys): a compiled radix sort.

numpy's stable sort of int64 keys is a merge sort (~80 ms for a million keys); the keys of a voxel
or cell grid are bounded by the grid's cell count, so a least-significant-digit radix sort of at
most 15 bits a pass does it in one or two passes over the keys (three beyond 30 bits). The
permutation is numpy's ``argsort(kind="stable")``, exactly.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel

__all__ = ["order_by_label", "sort_keys"]


def sort_keys(keys: np.ndarray, key_count: float, index_type=np.int64) -> tuple[np.ndarray, np.ndarray]:
    """``(order, sorted keys)`` of (N,) int32 or int64 ``keys`` in ``[0, key_count)``: ``order`` (``index_type``)
    is the stable sorting permutation (``np.argsort(keys, kind="stable")``) and the sorted keys are
    ``keys[order]``. ``keys`` is used as working space (its content is undefined afterwards)."""
    n = len(keys)
    bits = max(1, int(np.ceil(np.log2(float(key_count) + 1.0))))
    # at most 15 bits a pass (32,768 counts, 256 kB: they stay in the core's cache); fewer passes
    # over the keys beat smaller digits: 3 M keys of 30 bits sort in 55 ms (2 passes of 15 bits),
    # not 74 ms (3 of 10); 2.2 M of 24 bits in 36 ms, not 50 ms (3 of 8)
    passes = int(np.ceil(bits / 15))
    digit = int(np.ceil(bits / passes))
    order = np.empty(n, dtype=index_type)
    spare_keys, spare_order = np.empty_like(keys), np.empty_like(order)
    if _radix_argsort(keys, spare_keys, order, spare_order, digit, passes):
        return spare_order, spare_keys
    return order, keys


@kernel
def _radix_argsort(keys, spare_keys, order, spare_order, digit, passes):  # pragma: no cover - compiled
    """Stable least-significant-digit radix sort of non-negative ``keys`` (``digit`` bits per
    pass), ``order`` the sorting permutation. Returns True when the result ended in the spare
    arrays (an odd number of passes moved it there)."""
    n = keys.shape[0]
    for i in range(n):
        order[i] = i
    mask = (np.int64(1) << digit) - 1
    count = np.zeros((1 << digit) + 1, dtype=np.int64)
    in_spare = False
    for p in range(passes):
        shift = p * digit
        src_k, dst_k = (spare_keys, keys) if in_spare else (keys, spare_keys)
        src_o, dst_o = (spare_order, order) if in_spare else (order, spare_order)
        count[:] = 0
        for i in range(n):
            count[((src_k[i] >> shift) & mask) + 1] += 1
        if count.max() == n:  # one digit value: this pass would not move anything
            continue
        for d in range(1, count.shape[0]):
            count[d] += count[d - 1]
        for i in range(n):
            d = (src_k[i] >> shift) & mask
            j = count[d]
            count[d] = j + 1
            dst_k[j] = src_k[i]
            dst_o[j] = src_o[i]
        in_spare = not in_spare
    return in_spare


def order_by_label(labels: np.ndarray, index_type=np.int64) -> tuple[np.ndarray, np.ndarray]:
    """``(order, starts)`` of (N,) non-negative integer ``labels`` (tree ids, cluster ids):
    ``order`` (``index_type``) is the stable sorting permutation (``np.argsort(labels,
    kind="stable")``, exactly) and the rows of label ``v`` are ``order[starts[v]:starts[v + 1]]``
    (``starts``: (max label + 2,) int64). A counting sort: one pass to count, one to place, and no
    array but the permutation (4 bytes a row with int32, where ``argsort`` makes 8 and a merge
    buffer)."""
    labels = np.asarray(labels)
    if labels.ndim != 1:
        raise ValueError(f"labels must be one-dimensional, got shape {labels.shape}")
    if len(labels) and int(labels.min()) < 0:
        raise ValueError("labels must be non-negative")
    counts = np.zeros((int(labels.max()) if len(labels) else 0) + 1, dtype=np.int64)
    _count_labels(labels, counts)  # not np.bincount: it copies int32 labels to 8 bytes a row first
    starts = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    order = np.empty(len(labels), dtype=index_type)
    _place_by_label(labels, starts[:-1].copy(), order)
    return order, starts


@kernel
def _count_labels(labels, counts):  # pragma: no cover - compiled
    for i in range(labels.shape[0]):
        counts[labels[i]] += 1


@kernel
def _place_by_label(labels, next_slot, order):  # pragma: no cover - compiled
    """Each row's index into the next free slot of its label (rows in input order: stable)."""
    for i in range(labels.shape[0]):
        v = labels[i]
        order[next_slot[v]] = i
        next_slot[v] += 1
